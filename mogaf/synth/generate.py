"""Write a synthetic scene to disk in the DyCheck iPhone layout (+ ground truth).

Layout of `out_dir` (scale 1x only; frame name "<camera>_<time:05d>"):

    camera/<name>.json          DyCheck camera: orientation (w2c rotation), position
                                (centre), focal_length, principal_point, skew,
                                pixel_aspect_ratio, image_size [W, H], distortion 0
    rgb/1x/<name>.png           RGB, 2x2 supersampled
    depth/1x/<name>.npy         float32 (H, W, 1) camera-space z at pixel centres, every
                                frame of every camera (always valid: rays end on the
                                static ground / wall)
    covisible/1x/val/<name>.png uint8 0/255 for the held-out cameras (1, 2 by default): 255 where the surface seen
                                at the pixel centre is also visible from the train
                                camera at the same time (inside its image, first hit)
    points.npy                  (N, 3) float32 static background points (train view, t=0)
    splits/train.json           camera 0, every time
    splits/val.json             the held-out cameras (test_camera_yaw_deg: 1 to 3), every time
    dataset.json, metadata.json, scene.json (identity normalisation: centre 0,
    scale 1, near/far in metres), extra.json (bbox, factor 1, fps, lookat, up)
    flow3d_preprocessed/track_anything/1x/<name>.png
                                Shape-of-Motion style foreground mask (255 on dynamic
                                objects), every frame (SoM ships them for val frames too)
    mogaf_gt/instances.json     background id 0 + per object: id, name, rigid, kind,
                                pose_index (row in object_poses.npy or -1), shape
                                (box half_extents / sphere radius in the object frame,
                                cloth / arm dimensions, blob radius and squash), parts (the pieces that move
                                each as one: ["whole"], the arm's upper/lower, the
                                chest's body/lid)
    mogaf_gt/instance/1x/<name>.png   uint16 instance id at pixel centres, every frame
    mogaf_gt/part/1x/<name>.png uint8 index into its instance's parts at pixel centres
    mogaf_gt/points3d.npy       (P, T, 3) float32 world trajectories of surface points
    mogaf_gt/points_instance.npy (P,) int32 their instance ids
    mogaf_gt/points_part.npy    (P,) uint8 their index into their instance's parts
    mogaf_gt/tracks2d.npy       (P, T, 2) float32 their pixel coordinates in the train
                                camera (continuous, pixel centres at +0.5)
    mogaf_gt/visible.npy        (P, T) bool: inside the train image and the first
                                surface on the ray (ray-cast depth test, tolerance
                                1e-4 m (1 + z)) and of the point's own instance
    mogaf_gt/tracks2d_all.npy   (C, P, T, 2) and visible_all.npy (C, P, T): same for
                                every camera (0 = train, then the held-out ones)
    mogaf_gt/object_poses.npy   (K, T, 4, 4) float64 object-to-world poses of the rigid
                                objects (rows follow instances.json pose_index)
    mogaf_gt/object_pose_ids.npy (K,) int32 instance id of each row
    mogaf_gt/params.json        resolved generator parameters and derived facts

World units are metres, z up, ground z = 0. Generation is deterministic: the
same parameters give byte-identical files.
"""

from __future__ import annotations

import io
import json
import os
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..artefact import atomic_folder
from ..errors import MogafError
from .params import resolve_params
from .render import Renderer, camera_origin
from .world import LOOK_AT, UP, World, build_world

FORMAT = "mogaf-synthetic-iphone"
FORMAT_VERSION = 1
VIS_TOL = 1e-4  # metres per metre of (1 + depth) for ray-cast visibility


def frame_name(cam: int, ti: int) -> str:
    return f"{cam}_{ti:05d}"


def _write_json(path: Path, obj: Any) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as fh:
        json.dump(obj, fh, indent=2, sort_keys=True, allow_nan=False)
        fh.write("\n")


def _write_png(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if img.ndim == 3:
        img = img[..., ::-1]  # RGB -> BGR for OpenCV
    ok, encoded = cv2.imencode(".png", np.ascontiguousarray(img), [cv2.IMWRITE_PNG_COMPRESSION, 3])
    if not ok:
        raise MogafError(f"{path}: OpenCV could not encode the image")
    with open(path, "wb") as fh:  # a plain write, not cv2.imwrite: a full disk is an OSError with its errno
        fh.write(encoded.tobytes())


def _write_npy(path: Path, arr: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()  # numpy's own file writer reports a full disk without its errno
    np.save(buffer, arr, allow_pickle=False)
    with open(path, "wb") as fh:
        fh.write(buffer.getbuffer())


def camera_json(world: World, w2c: np.ndarray) -> dict[str, Any]:
    K = world.K
    return {
        "focal_length": float(K[0, 0]),
        "image_size": [world.width, world.height],
        "orientation": w2c[:3, :3].tolist(),
        "pixel_aspect_ratio": float(K[1, 1] / K[0, 0]),
        "position": camera_origin(w2c).tolist(),
        "principal_point": [float(K[0, 2]), float(K[1, 2])],
        "radial_distortion": [0.0, 0.0, 0.0],
        "skew": float(K[0, 1]),
        "tangential_distortion": [0.0, 0.0],
    }


def _track_points(world: World, rng: np.random.Generator):
    """GT surface points of every dynamic object: trajectories (P, T, 3), instance (P,), part (P,)."""
    n = world.params.num_track_points
    trajs, insts, parts = [], [], []
    for obj in world.objects:
        material = obj.sample_material(rng, n)
        trajs.append(np.stack([obj.points(material, float(tau)) for tau in world.taus], axis=1))
        insts.append(np.full(n, obj.inst, dtype=np.int32))
        parts.append(obj.point_parts(material).astype(np.uint8))
    return np.concatenate(trajs), np.concatenate(insts), np.concatenate(parts)


def _render_frame(
    world: World, renderer: Renderer, root: Path, ti: int, points3d: np.ndarray, points_inst: np.ndarray
) -> dict[str, Any]:
    """Every camera's view of frame ti, written; its tracks, visibility and depth range."""
    H, W = world.height, world.width
    P = len(points3d)
    tracks = np.zeros((world.num_cameras, P, 2))
    visible = np.zeros((world.num_cameras, P), dtype=bool)
    dmin, dmax = np.inf, 0.0
    bg_points = None
    train_w2c = world.camera_w2c(0, ti)
    for cam in range(world.num_cameras):
        name = frame_name(cam, ti)
        view = renderer.render(cam, ti)
        _write_png(root / "rgb" / "1x" / f"{name}.png", view.rgb)
        _write_npy(root / "depth" / "1x" / f"{name}.npy", view.depth.astype(np.float32)[..., None])
        _write_png(root / "mogaf_gt" / "instance" / "1x" / f"{name}.png", view.inst)
        _write_png(root / "mogaf_gt" / "part" / "1x" / f"{name}.png", view.part)
        dmin, dmax = min(dmin, float(view.depth.min())), max(dmax, float(view.depth.max()))
        w2c = world.camera_w2c(cam, ti)
        fg = np.where(view.inst > 0, 255, 0).astype(np.uint8)
        _write_png(root / "flow3d_preprocessed" / "track_anything" / "1x" / f"{name}.png", fg)
        if cam == 0:
            if ti == 0:
                bg_points = _background_points(world, w2c, view.depth, view.inst)
        else:
            covis = _covisible(world, renderer, w2c, train_w2c, view.depth, ti)
            _write_png(root / "covisible" / "1x" / "val" / f"{name}.png", np.where(covis, 255, 0).astype(np.uint8))
        # ground-truth tracks: projection + ray-cast visibility
        uv, z, t_hit, inst = renderer.first_hit(cam, ti, points3d[:, ti])
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
        visible[cam] = inside & (inst == points_inst) & (np.abs(t_hit - z) <= VIS_TOL * (1.0 + z))
        tracks[cam] = uv
    return {"tracks": tracks, "visible": visible, "depth_range": (dmin, dmax), "bg_points": bg_points}


def _render_all(
    world: World, root: Path, points3d: np.ndarray, points_inst: np.ndarray, threads: int = 1
) -> dict[str, Any]:
    """Every frame (_render_frame), on `threads` threads: a frame's views are
    independent of the others' (each computed as alone), and numpy's array
    operations release the interpreter lock, so threads overlap."""
    renderer = Renderer(world)
    renderer.cache_fixed_cameras()
    T = len(world.taus)

    def frame(ti: int) -> dict[str, Any]:
        return _render_frame(world, renderer, root, ti, points3d, points_inst)

    if threads > 1:
        with ThreadPoolExecutor(max_workers=threads) as pool:
            try:
                frames = list(pool.map(frame, range(T)))
            except BaseException:  # a failed frame (a full disk): the frames not started are not rendered
                pool.shutdown(cancel_futures=True)
                raise
    else:
        frames = [frame(ti) for ti in range(T)]
    return {
        "tracks": np.stack([f["tracks"] for f in frames], axis=2),
        "visible": np.stack([f["visible"] for f in frames], axis=2),
        "depth_range": (min(f["depth_range"][0] for f in frames), max(f["depth_range"][1] for f in frames)),
        "bg_points": frames[0]["bg_points"],
    }


def _background_points(world: World, w2c: np.ndarray, depth: np.ndarray, inst: np.ndarray) -> np.ndarray:
    """Back-project every other static pixel of a train view to world points (N, 3)."""
    H, W = depth.shape
    jj, ii = np.mgrid[0:H:2, 0:W:2]
    keep = inst[jj, ii] == 0
    u, v, z = ii[keep] + 0.5, jj[keep] + 0.5, depth[jj, ii][keep]
    K = world.K
    cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)
    R, t = w2c[:3, :3], w2c[:3, 3]
    return ((cam - t) @ R).astype(np.float32)


def _covisible(
    world: World, renderer: Renderer, w2c: np.ndarray, train_w2c: np.ndarray, depth: np.ndarray, ti: int
) -> np.ndarray:
    """Pixels of a test view whose surface point the train camera sees at the same time."""
    H, W = depth.shape
    K = world.K
    jj, ii = np.mgrid[0:H, 0:W]
    z = depth.ravel()
    cam = np.stack([(ii.ravel() + 0.5 - K[0, 2]) / K[0, 0] * z, (jj.ravel() + 0.5 - K[1, 2]) / K[1, 1] * z, z], axis=1)
    pts = (cam - w2c[:3, 3]) @ w2c[:3, :3]
    uv, zt, t_hit, _ = renderer.first_hit(0, ti, pts)
    inside = (zt > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    ok = inside & (np.abs(t_hit - zt) <= VIS_TOL * (1.0 + zt))
    return ok.reshape(H, W)


def _write_layout(root: Path, p: dict[str, Any], threads: int = 1) -> None:
    world = build_world(p)
    s = world.params
    T = len(world.taus)
    rng = np.random.default_rng([int(s.seed), 777])
    points3d, points_inst, points_part = _track_points(world, rng)
    out = _render_all(world, root, points3d, points_inst, threads)

    names = {cam: [frame_name(cam, ti) for ti in range(T)] for cam in range(world.num_cameras)}
    for cam in range(world.num_cameras):
        for ti in range(T):
            _write_json(root / "camera" / f"{names[cam][ti]}.json", camera_json(world, world.camera_w2c(cam, ti)))
    train_ids = names[0]
    val_cams = range(1, world.num_cameras)
    val_ids = [name for cam in val_cams for name in names[cam]]
    _write_json(
        root / "splits" / "train.json", {"frame_names": train_ids, "camera_ids": [0] * T, "time_ids": list(range(T))}
    )
    _write_json(
        root / "splits" / "val.json",
        {
            "frame_names": val_ids,
            "camera_ids": [c for c in val_cams for _ in range(T)],
            "time_ids": list(range(T)) * len(val_cams),
        },
    )
    _write_json(
        root / "dataset.json",
        {
            "count": world.num_cameras * T,
            "ids": train_ids + val_ids,
            "num_exemplars": T,
            "train_ids": train_ids,
            "val_ids": val_ids,
        },
    )
    _write_json(
        root / "metadata.json",
        {
            names[cam][ti]: {"appearance_id": ti, "camera_id": cam, "warp_id": ti}
            for cam in range(world.num_cameras)
            for ti in range(T)
        },
    )
    dmin, dmax = out["depth_range"]
    _write_json(
        root / "scene.json",
        {"center": [0.0, 0.0, 0.0], "scale": 1.0, "near": round(0.9 * dmin, 6), "far": round(1.1 * dmax, 6)},
    )
    bg = out["bg_points"]
    _write_npy(root / "points.npy", bg)
    centres = np.array([camera_origin(world.camera_w2c(c, ti)) for c in range(world.num_cameras) for ti in range(T)])
    allp = np.concatenate([bg, centres])
    _write_json(
        root / "extra.json",
        {
            "bbox": [allp.min(axis=0).tolist(), allp.max(axis=0).tolist()],
            "factor": 1,
            "fps": float(s.fps),
            "lookat": LOOK_AT.tolist(),
            "up": UP.tolist(),
        },
    )

    gt = root / "mogaf_gt"
    rigid_objs = [o for o in world.objects if o.rigid]
    pose_index = {o.inst: k for k, o in enumerate(rigid_objs)}
    _write_json(
        gt / "instances.json",
        {
            "background": 0,
            "instances": [
                {
                    "id": o.inst,
                    "name": o.name,
                    "rigid": bool(o.rigid),
                    "kind": o.kind,
                    "pose_index": pose_index.get(o.inst, -1),
                    "shape": o.shape(),
                    "parts": list(o.part_names),
                }
                for o in world.objects
            ],
        },
    )
    poses = (
        np.stack([np.stack([o.pose(float(tau)) for tau in world.taus]) for o in rigid_objs])
        if rigid_objs
        else np.zeros((0, T, 4, 4))
    )
    _write_npy(gt / "object_poses.npy", poses.astype(np.float64))
    _write_npy(gt / "object_pose_ids.npy", np.array([o.inst for o in rigid_objs], dtype=np.int32))
    _write_npy(gt / "points3d.npy", points3d.astype(np.float32))
    _write_npy(gt / "points_instance.npy", points_inst.astype(np.int32))
    _write_npy(gt / "points_part.npy", points_part)
    _write_npy(gt / "tracks2d.npy", out["tracks"][0].astype(np.float32))
    _write_npy(gt / "visible.npy", out["visible"][0])
    _write_npy(gt / "tracks2d_all.npy", out["tracks"].astype(np.float32))
    _write_npy(gt / "visible_all.npy", out["visible"])
    _write_json(
        gt / "params.json",
        {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "params": p,
            "num_frames": T,
            "sphere_bounce_times_s": world.info.get("sphere_bounce_times", []),
            **({"stick_time_s": world.info["stick_time"]} if "stick_time" in world.info else {}),
            "K": world.K.tolist(),
        },
    )


def generate_scene(out_dir: str | os.PathLike, params: Mapping[str, Any] | None = None, threads: int = 1) -> Path:
    """Generate the synthetic scene described by `params` into `out_dir`.

    `params` may name a preset ("preset": "default" | "hard") and override any
    key of DEFAULT_PARAMS. The folder is built in a hidden temporary sibling
    and renamed into place at the end (an existing folder is replaced), so a
    killed run never leaves a partial scene. `threads` frames render at once
    (the same files). Returns `out_dir`.
    """
    p = resolve_params(params)
    out = Path(out_dir)
    with atomic_folder(out) as tmp:
        _write_layout(tmp, p, threads)
    return out
