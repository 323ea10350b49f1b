"""D-NeRF / Blender layout (e.g. the MuJoCo scenes) -> Scene.

Files (val/test optional):
  transforms_{train,val,test}.json  camera_angle_x [camera_angle_y] or fl_x,
      fl_y, cx, cy, w, h (top level or per frame; per frame wins), frames:
      file_path, time in [0, 1], transform_matrix (OpenGL camera-to-world)
  <split>/<name>.png                RGBA (composited on the background colour)
                                    or RGB (alpha stays None)
  <split>/masks/<name>.png          optional object-id masks (0 = background)
  class_mapping.json                optional {"<id>": "<name>"} (scene folder
                                    or <split>/masks/)
  fused.ply                         optional point cloud (x, y, z [, r, g, b])

Stored:
- frame_names "<split>/<name>" in json order, train then val then test;
- camera_id = the frame's row: every D-NeRF frame is its own camera (a
  "teleporting" monocular capture), so no two frames share intrinsics or pose
  by construction;
- time as in the json; time_index on the uniform grid (see common.time_grid:
  T = number of distinct times over all splits when they lie on a uniform
  grid, or options["num_timesteps"] to snap);
- instances: ids of class_mapping.json except 0, rigidity from
  options["rigidity"] (first fnmatch pattern wins, else -1 unknown);
- meta: background, downscale, source_size [W, H], camera_id_rule,
  time_snap_error (in grid steps), point_cloud_has_color.

Options: downscale (int, default 1: area mean for colours/alpha, block
majority for ids, K scaled by 1/s exactly; sides that are not a multiple of s
lose their last rows/columns), background ([r, g, b] in [0, 1], default
white), rigidity (ordered mapping of fnmatch patterns to rigid | nonrigid),
num_timesteps (snap times to this grid), masks (default true), frame_stride
(read every k-th frame of each split; the time grid still uses all frames),
workers (decode threads).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..camera import GL_TO_CV, camera_centre_problem, intrinsics_matrix, pose_problem, rigid_inverse, scale_intrinsics
from ..errors import MogafError, input_error
from ..scene import MAX_TIMESTEPS, SPLIT_CODES, Instances, Scene
from .common import (
    as_array,
    as_float,
    as_image_side,
    as_list,
    as_str,
    load_json,
    option_background,
    option_bool,
    option_int,
    rigidity_of,
    rigidity_rules,
    time_grid,
    warn_dataset,
)
from .images import composite_downscale, downscale_area, downscale_labels, png_size, read_image, read_label_image
from .ply import read_ply_points

SPLITS = ("train", "val", "test")
INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x", "camera_angle_y")
MAX_MASK_ID = 1 << 16


@dataclass
class _Frame:
    name: str
    file_path: str
    split: str
    json_path: Path
    index: int  # position in its json
    image: Path
    mask: Path
    time: float
    c2w: np.ndarray
    intr: dict


def missing_message(scene_dir: Path, dataset: str, scene: str) -> str:
    return (
        f"{scene_dir}: D-NeRF scene '{scene}' of dataset '{dataset}' not found; put its transforms_train.json "
        f"(optional transforms_val.json, transforms_test.json), the split image folders, optional "
        f"<split>/masks/ with class_mapping.json, and optional fused.ply in this folder"
    )


def _image_path(scene_dir: Path, file_path: str) -> Path:
    rel = file_path[2:] if file_path.startswith("./") else file_path
    p = scene_dir / rel
    if not p.suffix or p.suffix.lower() not in (".png", ".jpg", ".jpeg"):
        p = p.with_name(p.name + ".png")
    return p


def _leaves_folder(file_path: str) -> bool:
    """An absolute path, or one whose '..' climbs out of the scene folder
    (read lexically: links inside the folder may point anywhere)."""
    normal = os.path.normpath(file_path)
    return os.path.isabs(file_path) or normal == ".." or normal.startswith(".." + os.sep)


def _warn_shared_times(frames: list[_Frame], time_index: dict[str, int]) -> None:
    """Two frames of one split at one time, while a time step of the split's
    span has no frame of it: a time was most likely copied wrong (the step
    it belongs to is then empty). Synchronised multi-view captures share
    times too, but leave no step empty, and are not warned about."""
    by_split: dict[str, list[_Frame]] = {}
    for fr in frames:
        by_split.setdefault(fr.split, []).append(fr)
    for split_frames in by_split.values():
        first: dict[float, _Frame] = {}
        pair = None
        for fr in split_frames:
            if fr.time in first and pair is None:
                pair = (first[fr.time], fr)
            first.setdefault(fr.time, fr)
        if pair is None:
            continue
        steps = np.array(sorted({time_index[fr.name] for fr in split_frames}))
        empty = np.setdiff1d(np.arange(steps[0], steps[-1] + 1), steps)
        if not empty.size:
            continue
        a, b = pair
        listed = ", ".join(str(int(t)) for t in empty[:5]) + (", ..." if empty.size > 5 else "")
        warn_dataset(
            a.json_path,
            f"frames {a.index} ({a.file_path}) and {b.index} ({b.file_path}) share time "
            f"{a.time:g}, and time step(s) {listed} of its frames' span have no frame: "
            "a frame time is probably wrong",
        )


def _parse_split(scene_dir: Path, split: str) -> list[_Frame]:
    path = scene_dir / f"transforms_{split}.json"
    data = load_json(path, what=f"D-NeRF {split} cameras")
    top = {k: data[k] for k in INTRINSIC_KEYS if k in data}
    frames = as_list(data.get("frames"), path, "'frames'") if "frames" in data else None
    if frames is None:
        raise input_error(path, "missing key 'frames'")
    if not frames:
        raise input_error(path, "lists no frames ('frames' is empty); add its frames or remove the file")
    out: list[_Frame] = []
    for i, fr in enumerate(frames):
        where = f"frame {i}"
        if not isinstance(fr, dict):
            raise input_error(path, f"{where} must be an object")
        if "file_path" not in fr:
            raise input_error(path, f"{where}: missing key 'file_path'")
        file_path = as_str(fr["file_path"], path, f"{where} file_path")
        if len(file_path) > 1024 or any(len(part) > 200 for part in file_path.split("/")):
            raise input_error(path, f"{where}: file_path is too long")
        if os.path.normpath(file_path) == ".":
            raise input_error(path, f"{where}: file_path {file_path!r} names the scene folder, not an image")
        if _leaves_folder(file_path):
            raise input_error(
                path,
                f"{where}: file_path {file_path!r} leaves the scene folder; "
                "image paths must be relative to it and stay inside it",
            )
        where = f"frame {i} ({file_path})"
        if "time" not in fr:
            raise input_error(path, f"{where}: missing key 'time'")
        t = as_float(fr["time"], path, f"{where} time", lo=0.0, hi=1.0)
        if "transform_matrix" not in fr:
            raise input_error(path, f"{where}: missing key 'transform_matrix'")
        c2w = as_array(fr["transform_matrix"], (4, 4), path, f"{where} transform_matrix")
        problem = pose_problem(c2w)
        if problem:
            raise input_error(path, f"{where}: transform_matrix is not a rigid camera pose: {problem}")
        intr = dict(top)
        intr.update({k: fr[k] for k in INTRINSIC_KEYS if k in fr})
        image = _image_path(scene_dir, file_path)
        stem = image.stem
        rel = file_path[2:] if file_path.startswith("./") else file_path
        name = os.path.splitext(rel)[0] if Path(rel).suffix.lower() in (".png", ".jpg", ".jpeg") else rel
        out.append(
            _Frame(
                name=name,
                file_path=file_path,
                split=split,
                json_path=path,
                index=i,
                image=image,
                mask=image.parent / "masks" / f"{stem}.png",
                time=t,
                c2w=c2w,
                intr=intr,
            )
        )
    return out


def _intrinsics(fr: _Frame, width: int, height: int) -> np.ndarray:
    """K at the source resolution; checks JSON w/h against the image."""
    path, where, d = fr.json_path, f"frame {fr.index} ({fr.file_path})", fr.intr
    for key, actual in (("w", width), ("h", height)):
        if key in d:
            value = as_image_side(d[key], path, f"{where} {key}")
            if value != actual:
                raise input_error(fr.image, f"image is {width}x{height}, but {path.name} says {key}={value}")
    if "fl_x" in d:
        fx = as_float(d["fl_x"], path, f"{where} fl_x", positive=True)
    elif "camera_angle_x" in d:
        ang = as_float(d["camera_angle_x"], path, f"{where} camera_angle_x", positive=True)
        if ang >= math.pi:
            raise input_error(path, f"{where}: camera_angle_x must be below pi, got {ang:g}")
        fx = 0.5 * width / math.tan(0.5 * ang)
    else:
        raise input_error(path, f"{where}: no focal length (camera_angle_x or fl_x)")
    if "fl_y" in d:
        fy = as_float(d["fl_y"], path, f"{where} fl_y", positive=True)
    elif "camera_angle_y" in d:
        ang = as_float(d["camera_angle_y"], path, f"{where} camera_angle_y", positive=True)
        if ang >= math.pi:
            raise input_error(path, f"{where}: camera_angle_y must be below pi, got {ang:g}")
        fy = 0.5 * height / math.tan(0.5 * ang)
    else:
        fy = fx
    cx = as_float(d["cx"], path, f"{where} cx") if "cx" in d else width / 2.0
    cy = as_float(d["cy"], path, f"{where} cy") if "cy" in d else height / 2.0
    if not (math.isfinite(fx) and math.isfinite(fy) and fx > 0 and fy > 0):
        raise input_error(path, f"{where}: focal length must be positive and finite")
    return intrinsics_matrix(fx, fy, cx, cy)


def _class_mapping(scene_dir: Path, frames: list[_Frame]) -> tuple[dict[int, str] | None, Path | None]:
    candidates = [scene_dir / "class_mapping.json"]
    for fr in frames:
        c = fr.mask.parent / "class_mapping.json"
        if c not in candidates:
            candidates.append(c)
    for path in candidates:
        if path.exists():
            raw = load_json(path, what="class mapping")
            mapping: dict[int, str] = {}
            spelled: dict[int, str] = {}
            for key, value in raw.items():
                try:
                    k = int(key)
                except ValueError:
                    raise input_error(path, f"class id {key!r} is not an integer") from None
                if not (0 <= k < MAX_MASK_ID):
                    raise input_error(path, f"class id {k} is outside [0, {MAX_MASK_ID})")
                if k in mapping:  # e.g. "1" and "01": the last would win silently
                    raise input_error(path, f"class id {k} is listed twice ({spelled[k]!r} and {key!r}); keep one")
                mapping[k] = as_str(value, path, f"name of class {k}")
                spelled[k] = key
            return mapping, path
    return None, None


def _read_all_frames(scene_dir: Path, scene: str) -> list[_Frame]:
    """Every frame of every split's json (train then val then test), each listed once."""
    if not (scene_dir / "transforms_train.json").exists():
        raise input_error(scene_dir / "transforms_train.json", f"missing (the D-NeRF train cameras of scene '{scene}')")
    all_frames: list[_Frame] = []
    for split in SPLITS:
        if split == "train" or (scene_dir / f"transforms_{split}.json").exists():
            all_frames.extend(_parse_split(scene_dir, split))
    seen: dict[str, _Frame] = {}
    for fr in all_frames:
        if fr.name in seen:
            raise input_error(fr.json_path, f"frame {fr.index} ({fr.file_path}) is listed twice")
        seen[fr.name] = fr
    return all_frames


def _source_size(first: _Frame, s: int) -> tuple[int, int]:
    """(W, H) of the first image (header only when it is a PNG), checked against the downscale factor."""
    header = png_size(first.image)
    if header is None:
        probe = read_image(first.image)
        W0, H0 = probe.shape[1], probe.shape[0]
    else:
        W0, H0 = header[0], header[1]
    if s > W0 or s > H0:
        raise input_error(first.image, f"image {W0}x{H0} is smaller than the downscale factor {s}")
    return W0, H0


class _Decoded:
    """The scene's images, alpha and masks at the output size, filled frame by frame by `load`."""

    def __init__(
        self,
        frames: list[_Frame],
        source_size: tuple[int, int],
        downscale: int,
        background: np.ndarray,
        has_masks: bool,
        mapping: dict[int, str] | None,
        mapping_path: Path | None,
    ) -> None:
        F, s = len(frames), downscale
        h, w = source_size[1] // s, source_size[0] // s
        self.frames, self.source_size, self.downscale, self.background = frames, source_size, s, background
        self.mapping, self.mapping_path = mapping, mapping_path
        # An empty mapping lists no id: every non-zero mask id is then unknown (not "anything goes").
        self.known_ids = np.array(sorted(mapping), dtype=np.int64) if mapping is not None else None
        self.images = np.empty((F, h, w, 3), np.uint8)
        self.alpha = np.full((F, h, w), 255, np.uint8)
        self.has_alpha = np.zeros(F, bool)
        self.masks = np.zeros((F, h, w), np.int32) if has_masks else None
        self.ids_seen = np.zeros(MAX_MASK_ID, bool) if has_masks else None

    def load(self, f: int) -> None:
        fr = self.frames[f]
        try:
            self._load_image(f, fr)
            if self.masks is not None:
                self._load_mask(f, fr)
        except cv2.error as exc:
            raise input_error(
                fr.image, f"image processing failed ({str(exc).splitlines()[0] if str(exc) else 'cv2 error'})"
            ) from None

    def _load_image(self, f: int, fr: _Frame) -> None:
        s = self.downscale
        img = read_image(fr.image, expect_size=self.source_size)
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        if img.shape[2] == 4:
            self.has_alpha[f] = True
            self.images[f], self.alpha[f] = composite_downscale(img, self.background, s)
        else:
            self.images[f] = downscale_area(img[..., :3], s)

    def _load_mask(self, f: int, fr: _Frame) -> None:
        if not fr.mask.exists():
            raise input_error(fr.mask, f"missing object-id mask for frame {fr.name} (other frames have masks)")
        m = read_label_image(fr.mask, expect_size=self.source_size)
        present = np.flatnonzero(np.bincount(m.ravel()))
        if self.known_ids is not None:
            self._check_mask_ids(fr, present)
        self.ids_seen[present] = True
        self.masks[f] = downscale_labels(m, self.downscale, present)

    def _check_mask_ids(self, fr: _Frame, present: np.ndarray) -> None:
        """Every object id of the mask is listed in the class mapping."""
        unknown = np.setdiff1d(present, self.known_ids)
        objects = unknown[unknown != 0]
        if not self.mapping and objects.size:
            raise input_error(
                self.mapping_path,
                f"lists no class, but the mask {fr.mask} has object id "
                f"{int(objects[0])}; list every id of the masks (0 = background)",
            )
        if self.mapping and unknown.size:
            raise input_error(fr.mask, f"mask has id {int(unknown[0])} that {self.mapping_path.name} does not list")

    def load_all(self, workers: int) -> None:
        F = len(self.frames)
        if workers <= 1 or F <= 1:
            for f in range(F):
                self.load(f)
        else:
            with ThreadPoolExecutor(max_workers=workers) as pool:
                # list() re-raises the first failure (in frame order).
                list(pool.map(self.load, range(F)))

    def check_alpha(self) -> None:
        """Refuse a mix of frames with and without alpha."""
        frames, has_alpha = self.frames, self.has_alpha
        if has_alpha.any() and not has_alpha.all():
            # its background cannot be replaced like the others': refuse rather than mix two backgrounds
            rgb, rgba = frames[int(np.argmin(has_alpha))], frames[int(np.argmax(has_alpha))]
            raise input_error(
                rgb.image,
                f"image has no alpha channel, but other frames of the scene do (e.g. {rgba.file_path}): "
                "give every frame an alpha channel or none, so that one background applies to all",
            )


def _instances(mapping: dict[int, str] | None, ids_seen: np.ndarray, rules: list) -> Instances:
    """The mask's instances: those of the class mapping, else every id seen in a mask."""
    if mapping is None:
        ids = np.flatnonzero(ids_seen)
        mapping = {int(i): f"id{int(i)}" for i in ids}
        mapping[0] = "background"
    inst_ids = np.array(sorted(k for k in mapping if k != 0), dtype=np.int64)
    names = [mapping[int(i)] for i in inst_ids]
    return Instances(ids=inst_ids, names=names, rigid=np.array([rigidity_of(n, rules) for n in names], dtype=np.int8))


def read_dnerf_scene(
    scene_dir: str | os.PathLike, *, dataset: str, scene: str, options: Mapping | None = None
) -> Scene:
    scene_dir = Path(scene_dir)
    options = dict(options or {})
    if not scene_dir.is_dir():
        raise MogafError(missing_message(scene_dir, dataset, scene))
    where = f"dataset '{dataset}' options"
    s = option_int(options, "downscale", 1, hi=64, where=where)
    stride = option_int(options, "frame_stride", 1, hi=1 << 20, where=where)
    workers = option_int(options, "workers", min(8, os.cpu_count() or 1), hi=64, where=where)
    background = option_background(options, where=where)
    rules = rigidity_rules(options, where=where)
    T_opt = options.get("num_timesteps")
    if T_opt is not None:
        T_opt = option_int(options, "num_timesteps", 1, lo=1, hi=MAX_TIMESTEPS, where=where)
    use_masks = option_bool(options, "masks", True, where=where)

    all_frames = _read_all_frames(scene_dir, scene)
    # Time grid over every frame of every split (before any stride).
    idx_all, T, snap_err = time_grid(
        np.array([fr.time for fr in all_frames]), scene_dir / "transforms_train.json", T_opt
    )
    time_index_of = {fr.name: int(i) for fr, i in zip(all_frames, idx_all)}
    _warn_shared_times(all_frames, time_index_of)

    frames: list[_Frame] = []
    for split in SPLITS:
        frames.extend([fr for fr in all_frames if fr.split == split][::stride])

    W0, H0 = _source_size(frames[0], s)
    K_all = np.stack([scale_intrinsics(_intrinsics(fr, W0, H0), 1.0 / s) for fr in frames])

    has_masks = use_masks and any(fr.mask.parent.is_dir() for fr in frames)
    mapping, mapping_path = _class_mapping(scene_dir, frames) if has_masks else (None, None)

    F = len(frames)
    decoded = _Decoded(frames, (W0, H0), s, background, has_masks, mapping, mapping_path)
    decoded.load_all(workers)
    if decoded.masks is not None and not decoded.masks.any():
        warn_dataset(
            frames[0].mask.parent,
            "every object-id mask is all background (id 0): grouping has no object to start from, "
            "and a scene without depth has no foreground to reconstruct; fix the masks or set the "
            "dataset option masks: false",
        )
    decoded.check_alpha()
    w2c = np.stack([rigid_inverse(fr.c2w @ GL_TO_CV) for fr in frames])
    outlier = camera_centre_problem(w2c)
    if outlier is not None:
        fr = frames[outlier[0]]
        raise input_error(fr.json_path, f"frame {fr.index} ({fr.file_path}): {outlier[1]}")
    instances = _instances(mapping, decoded.ids_seen, rules) if has_masks else None

    point_cloud, pc_colour = None, None
    ply = scene_dir / "fused.ply"
    if ply.exists():
        point_cloud, pc_colour = read_ply_points(ply)

    meta = {
        "background": [float(x) for x in background],
        "downscale": s,
        "source_size": [int(W0), int(H0)],
        "camera_id_rule": "per-frame: every D-NeRF frame is its own camera (camera_id = row)",
        "time_snap_error": float(snap_err),
        "frame_stride": stride,
    }
    if pc_colour is not None:
        meta["point_cloud_has_color"] = bool(pc_colour)
    out = Scene(
        dataset=dataset,
        name=scene,
        layout="dnerf",
        frame_names=[fr.name for fr in frames],
        images=decoded.images,
        K=K_all,
        w2c=w2c,
        time=np.array([fr.time for fr in frames], dtype=np.float64),
        time_index=np.array([time_index_of[fr.name] for fr in frames], dtype=np.int64),
        num_timesteps=int(T),
        camera_id=np.arange(F, dtype=np.int64),
        source_split=np.array([SPLIT_CODES[fr.split] for fr in frames], dtype=np.int8),
        alpha=decoded.alpha if decoded.has_alpha.any() else None,
        instance_mask=decoded.masks,
        instances=instances,
        point_cloud=point_cloud,
        meta=meta,
    )
    out.validate(scene_dir)
    return out
