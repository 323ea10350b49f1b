"""DyCheck iPhone JSON metadata: the train/val splits, the per-frame camera
jsons, scene.json/extra.json (kept in meta) and the train keypoints."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...camera import intrinsics_matrix, pose_problem, w2c_from_orientation_position
from ...errors import input_error
from ..common import MAX_IMAGE_SIDE, as_array, as_float, as_image_side, as_int, as_list, as_str, load_json

MAX_TIME_ID = 1 << 20
MAX_NAME = 120  # track files are named <query>_<target>.npy: two names must fit in 255 bytes


def _read_split(path: Path) -> tuple[list[str], list[int], list[int]]:
    data = load_json(path, what="DyCheck split")
    names = as_list(data.get("frame_names"), path, "'frame_names'") if "frame_names" in data else None
    if names is None:
        raise input_error(path, "missing key 'frame_names'")
    for key in ("camera_ids", "time_ids"):
        if key not in data:
            raise input_error(path, f"missing key '{key}'")
    cams = as_list(data["camera_ids"], path, "'camera_ids'")
    times = as_list(data["time_ids"], path, "'time_ids'")
    if not (len(names) == len(cams) == len(times)):
        raise input_error(
            path, f"frame_names, camera_ids and time_ids differ in length ({len(names)}, {len(cams)}, {len(times)})"
        )
    out_names = []
    for i, n in enumerate(names):
        n = as_str(n, path, f"frame_names[{i}]")
        if "/" in n or "\\" in n or n in (".", "..") or len(n) > MAX_NAME:
            raise input_error(
                path, f"frame_names[{i}] {n[:40]!r} is not a plain file name (at most {MAX_NAME} characters, no '/')"
            )
        out_names.append(n)
    out_cams = [as_int(c, path, f"camera_ids[{i}]", lo=0, hi=1 << 31) for i, c in enumerate(cams)]
    out_times = [as_int(t, path, f"time_ids[{i}]", lo=0, hi=MAX_TIME_ID) for i, t in enumerate(times)]
    return out_names, out_cams, out_times


def _read_camera(path: Path) -> dict:
    d = load_json(path, what="DyCheck camera")
    for key in ("orientation", "position", "focal_length", "principal_point", "image_size"):
        if key not in d:
            raise input_error(path, f"missing key '{key}'")
    R = as_array(d["orientation"], (3, 3), path, "orientation")
    c = as_array(d["position"], (3,), path, "position")
    f = as_float(d["focal_length"], path, "focal_length", positive=True)
    pp = as_array(d["principal_point"], (2,), path, "principal_point")
    ratio = as_float(d.get("pixel_aspect_ratio", 1.0), path, "pixel_aspect_ratio", positive=True)
    skew = as_float(d.get("skew", 0.0), path, "skew")
    size = as_list(d["image_size"], path, "image_size")
    if len(size) != 2:
        raise input_error(path, f"image_size must be [width, height], got {len(size)} entries")
    W = as_image_side(size[0], path, "image_size width")
    H = as_image_side(size[1], path, "image_size height")
    radial = (
        as_array(d["radial_distortion"], (3,), path, "radial_distortion")
        if d.get("radial_distortion") is not None
        else np.zeros(3)
    )
    tangential = (
        as_array(d["tangential_distortion"], (2,), path, "tangential_distortion")
        if d.get("tangential_distortion") is not None
        else np.zeros(2)
    )
    w2c = w2c_from_orientation_position(R, c)
    problem = pose_problem(w2c)
    if problem:
        raise input_error(path, f"orientation is not a camera rotation: {problem}")
    if f * ratio <= 0 or not np.isfinite(f * ratio):
        raise input_error(path, "focal_length * pixel_aspect_ratio must be positive and finite")
    return {
        "K": intrinsics_matrix(f, f * ratio, pp[0], pp[1], skew),
        "w2c": w2c,
        "size": (W, H),
        "radial": radial,
        "tangential": tangential,
    }


def _scene_meta(scene_dir: Path, meta: dict) -> None:
    spath = scene_dir / "scene.json"
    if spath.exists():
        sd = load_json(spath, what="DyCheck scene normalisation")
        if "center" in sd:
            meta["scene_center"] = as_array(sd["center"], (3,), spath, "center").tolist()
        if "scale" in sd:
            meta["scene_scale"] = as_float(sd["scale"], spath, "scale", positive=True)
        for key in ("near", "far"):
            if key in sd:
                meta[key] = as_float(sd[key], spath, key, lo=0.0)
    epath = scene_dir / "extra.json"
    if epath.exists():
        ed = load_json(epath, what="DyCheck extra")
        if "fps" in ed:
            meta["fps"] = as_float(ed["fps"], epath, "fps", positive=True)
        if "factor" in ed:
            meta["default_scale"] = as_int(ed["factor"], epath, "factor", lo=1, hi=MAX_IMAGE_SIDE)
        for key, shape in (("bbox", (2, 3)), ("lookat", (3,)), ("up", (3,))):
            if key in ed:
                meta[key] = as_array(ed[key], shape, epath, key).tolist()


def _keypoints(scene_dir: Path, S: int, names, splits, time_index, shipped: dict, h: int, w: int) -> None:
    """DyCheck keypoints (pixel indices, +0.5 -> continuous); 2x rescaled."""
    factor = 1.0
    kdir = scene_dir / "keypoint" / f"{S}x" / "train"
    if not kdir.is_dir():
        kdir = scene_dir / "keypoint" / "2x" / "train"
        factor = 2.0 / S
        if not kdir.is_dir():
            return
    rows, values = [], []
    J = None
    for f, (name, split) in enumerate(zip(names, splits)):
        path = kdir / f"{name}.json"
        if split != "train" or not path.exists():
            continue
        raw = load_json(path, what="DyCheck keypoints", expect=list)
        if J is None:
            J = len(raw)
        if len(raw) != J:
            raise input_error(path, f"has {len(raw)} keypoints, other frames have {J}")
        kp = as_array(raw, (J, 3), path, "keypoints") if J else np.zeros((0, 3))
        vis = (kp[:, 2] > 0).astype(np.float64)
        xy = (kp[:, :2] + 0.5) * factor * vis[:, None]
        rows.append(f)
        values.append(np.concatenate([xy, vis[:, None]], axis=1))
    if rows:
        shipped["keypoints"] = {
            "frame": np.array(rows, np.int64),
            "time_index": np.asarray(time_index)[rows],
            "values": np.stack(values).astype(np.float32),
        }
