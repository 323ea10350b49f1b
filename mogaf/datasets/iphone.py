"""DyCheck iPhone layout (+ Shape-of-Motion's preprocessing) -> Scene.

DyCheck files read (S = options["scale"], default 2):
  splits/train.json, splits/val.json   frame_names, camera_ids, time_ids
                                       (val optional)
  camera/<name>.json                   orientation (w2c rotation), position
                                       (camera centre), focal_length,
                                       principal_point, pixel_aspect_ratio
                                       (fy = fx * ratio), skew, image_size
                                       [W, H] at full resolution,
                                       radial/tangential_distortion
  dataset.json, metadata.json          optional cross-checks (ids, count,
                                       camera_id, warp_id = time index)
  scene.json, extra.json               optional; kept in meta
  rgb/<S>x/<name>.png                  RGB or RGBA; A is DyCheck's valid-pixel
                                       mask -> Scene.alpha (colours are NOT
                                       composited)
  depth/<S>x/<name>.npy                optional (H, W[, 1]) projective depth
                                       (0 = invalid) -> Scene.depth; frames
                                       without a file (held-out) get 0
  covisible/<S>x/val/<name>.png        optional -> Scene.covisible (1 where
                                       covisible; training frames are all 1)
  keypoint/<S>x/train/<name>.json      optional (J, 3) [x, y, visible]; when
                                       only keypoint/2x exists it is rescaled
  points.npy                           optional (N, 3) background points ->
                                       point_cloud (grey: no colours)

Shape-of-Motion files read (under flow3d_preprocessed/):
  track_anything/<S>x/<name>.png       foreground masks (SoM reads value/255
                                       and thresholds at 0.5) -> instance_mask
                                       with one instance "foreground" (id 1)
  aligned_<som_depth>/<S>x/<name>.npy  disparity (SoM inverts it to depth),
                                       som_depth default depth_anything_colmap
  2d_tracks/<S>x/<q>_<t>.npy           (P, 4) TAPIR tracks of the points
                                       queried in train frame q, seen in
                                       train frame t: x, y, occlusion logit,
                                       expected-distance logit
  covisible/<S>x/val/<name>.png        used when DyCheck's covisible/ is absent

Stored in Scene.shipped (frames are rows of the scene, in its order):
  disparity: frame (N,), time_index (N,), values (N, H, W) float32
  keypoints: frame (N,), time_index (N,), values (N, J, 3) float32
             [x, y, visible] in continuous pixel coordinates (centres +0.5)
  tracks_2d: query_frame (Q,), query_time_index (Q,), target_frame (M,),
             target_time_index (M,), offsets (Q+1,) int64, values
             (offsets[-1], M, 4) float32: the points of query q are rows
             offsets[q]:offsets[q+1]; x, y converted to the +0.5 pixel-centre
             convention (SoM/TAPIR put pixel centres at integers)
  distortion (only when some camera has non-zero distortion):
             frame (N,), radial (N, 3), tangential (N, 2)

Decisions: the world is NOT rescaled (camera jsons as they are; DyCheck's
center/scale/near/far go to meta, near/far being in DyCheck's normalised
units); distortion is recorded and a warning issued, images are not
undistorted (the DyCheck iPhone captures have zero distortion); frame order is
train then val, as listed; time_index = time_ids, num_timesteps = max + 1 over
both splits, time = time_index / (num_timesteps - 1).

Options: scale (2), depth (true), priors (true: SoM files), som_depth,
tracks (true), tracks_query_stride (1), tracks_max_points (256; 0 = all),
rigidity (patterns for "foreground"), workers.
"""

from __future__ import annotations

import os
import threading
import warnings
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from ..camera import intrinsics_matrix, pose_problem, scale_intrinsics, w2c_from_orientation_position
from ..errors import MogafError, input_error
from ..scene import SPLIT_CODES, Instances, Scene
from .common import (
    MAX_IMAGE_SIDE,
    as_array,
    as_float,
    as_image_side,
    as_int,
    as_list,
    as_str,
    load_json,
    option_bool,
    option_int,
    rigidity_of,
    rigidity_rules,
)
from .images import read_image

SPLITS = ("train", "val")
MAX_TIME_ID = 1 << 20
MAX_NAME = 120  # track files are named <query>_<target>.npy: two names must fit in 255 bytes
SOM = "flow3d_preprocessed"


# np.load parses .npy headers with ast.literal_eval, which CPython 3.11 does not
# allow from several threads at once (spurious "AST constructor recursion depth
# mismatch" SystemError): headers are parsed one at a time, data is read lazily.
_NPY_LOCK = threading.Lock()


def _open_npy(path: Path):
    with _NPY_LOCK:
        return np.load(path, mmap_mode="r", allow_pickle=False)


class DistortionWarning(UserWarning):
    """Some iPhone camera has non-zero lens distortion (images not undistorted)."""


def missing_message(scene_dir: Path, dataset: str, scene: str) -> str:
    return (
        f"{scene_dir}: DyCheck iPhone scene '{scene}' of dataset '{dataset}' not found; download DyCheck's "
        f"'{scene}' (camera/, rgb/<S>x/, depth/, covisible/, keypoint/, splits/, dataset.json, metadata.json, "
        f"scene.json, extra.json) into this folder, and unpack Shape-of-Motion's preprocessing of it "
        f"({SOM}/ with track_anything/, aligned_depth_anything_colmap/, 2d_tracks/) inside it"
    )


# ---------------------------------------------------------------- metadata
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


def _load_npy(path: Path, shape2d: tuple[int, int], what: str) -> np.ndarray:
    """A float (H, W) or (H, W, 1) array, header-checked before reading."""
    try:
        arr = _open_npy(path)
    except FileNotFoundError:
        raise input_error(path, f"missing {what}") from None
    except (ValueError, OSError, EOFError, TypeError) as exc:
        raise input_error(
            path,
            f"unreadable or corrupt .npy {what} ({str(exc).splitlines()[0] if str(exc) else exc.__class__.__name__})",
        ) from None
    if not isinstance(arr, np.ndarray):
        raise input_error(path, f"{what} is not a plain array")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.shape != shape2d:
        raise input_error(path, f"{what} has shape {arr.shape}, expected {shape2d} (the rgb image size)")
    if arr.dtype.kind not in "fiu":
        raise input_error(path, f"{what} has dtype {arr.dtype}, expected numbers")
    try:
        out = np.array(arr, dtype=np.float32)
    except (ValueError, OSError) as exc:
        raise input_error(path, f"unreadable or truncated .npy {what} ({exc.__class__.__name__})") from None
    if not np.all(np.isfinite(out)):
        raise input_error(path, f"{what} has NaN or infinite values")
    return out


def _load_tracks(path: Path) -> np.ndarray:
    try:
        arr = _open_npy(path)
    except FileNotFoundError:
        raise input_error(path, "missing 2D-track file (every train frame pair must have one)") from None
    except (ValueError, OSError, EOFError, TypeError) as exc:
        raise input_error(path, f"unreadable or corrupt .npy tracks ({exc.__class__.__name__})") from None
    if not isinstance(arr, np.ndarray) or arr.ndim != 2 or arr.shape[1] != 4 or arr.dtype.kind not in "fiu":
        raise input_error(path, f"2D tracks must be a (P, 4) numeric array, got {getattr(arr, 'shape', '?')}")
    return arr


def _binary_mask(path: Path, size: tuple[int, int], what: str) -> np.ndarray:
    img = read_image(path, expect_size=size, what=what)
    if img.ndim == 3:
        img = img[..., :3].max(axis=2) if img.shape[2] >= 3 else img.max(axis=2)
    thr = 1 if int(img.max(initial=0)) <= 1 else 128
    return (img >= thr).astype(np.uint8)


# ---------------------------------------------------------------- reader
def read_iphone_layout(scene_dir: str | os.PathLike, dataset: str, scene: str, options: Mapping | None = None) -> Scene:
    """Read a DyCheck iPhone scene folder (and SoM priors in it) into a Scene."""
    scene_dir = Path(scene_dir)
    options = dict(options or {})
    where = f"dataset '{dataset}' options"
    if not scene_dir.is_dir():
        raise MogafError(missing_message(scene_dir, dataset, scene))
    S = option_int(options, "scale", 2, hi=64, where=where)
    use_depth = option_bool(options, "depth", True, where=where)
    use_priors = option_bool(options, "priors", True, where=where)
    use_tracks = option_bool(options, "tracks", True, where=where)
    q_stride = option_int(options, "tracks_query_stride", 1, where=where)
    max_points = option_int(options, "tracks_max_points", 256, lo=0, hi=1 << 24, where=where)
    workers = option_int(options, "workers", min(8, os.cpu_count() or 1), hi=64, where=where)
    som_depth = options.get("som_depth", "depth_anything_colmap")
    if not isinstance(som_depth, str) or not som_depth or "/" in som_depth:
        raise MogafError(
            f"{where}: 'som_depth' must be a folder suffix such as depth_anything_colmap, got {som_depth!r}"
        )
    rules = rigidity_rules(options, where=where)

    # Splits.
    names: list[str] = []
    cams: list[int] = []
    tids: list[int] = []
    splits: list[str] = []
    listed_in: dict[str, Path] = {}
    train_path = scene_dir / "splits" / "train.json"
    if not train_path.exists():
        raise input_error(train_path, f"missing (the DyCheck train split of scene '{scene}')")
    for split in SPLITS:
        path = scene_dir / "splits" / f"{split}.json"
        if split != "train" and not path.exists():
            continue
        n, c, t = _read_split(path)
        for name in n:
            if name in listed_in:
                raise input_error(path, f"frame {name} is listed twice (also in {listed_in[name].name})")
            listed_in[name] = path
        names += n
        cams += c
        tids += t
        splits += [split] * len(n)
    if not names:
        raise input_error(train_path, "lists no frames")
    F = len(names)

    # Optional cross-checks with dataset.json / metadata.json.
    ids: set[str] | None = None
    dpath = scene_dir / "dataset.json"
    if dpath.exists():
        dd = load_json(dpath, what="DyCheck dataset")
        if "ids" in dd:
            id_list = [as_str(x, dpath, f"ids[{i}]") for i, x in enumerate(as_list(dd["ids"], dpath, "'ids'"))]
            ids = set(id_list)
            if "count" in dd and as_int(dd["count"], dpath, "count", lo=0) != len(id_list):
                raise input_error(dpath, f"count is {dd['count']} but ids lists {len(id_list)} frames")
            for name in names:
                if name not in ids:
                    raise input_error(listed_in[name], f"frame {name} is not among the ids of dataset.json")
    mpath = scene_dir / "metadata.json"
    if mpath.exists():
        md = load_json(mpath, what="DyCheck metadata")
        for name, cam, t in zip(names, cams, tids):
            if name not in md:
                raise input_error(mpath, f"has no entry for frame {name} (listed in {listed_in[name].name})")
            entry = md[name]
            if not isinstance(entry, dict):
                raise input_error(mpath, f"entry {name} must be an object")
            if "camera_id" in entry and as_int(entry["camera_id"], mpath, f"{name} camera_id") != cam:
                raise input_error(
                    mpath, f"frame {name}: camera_id {entry['camera_id']} differs from {listed_in[name].name} ({cam})"
                )
            if "warp_id" in entry and as_int(entry["warp_id"], mpath, f"{name} warp_id") != t:
                raise input_error(
                    mpath,
                    f"frame {name}: warp_id {entry['warp_id']} differs from the time_id in {listed_in[name].name} ({t})",
                )

    # Cameras: one per listed frame, none left over.
    cam_dir = scene_dir / "camera"
    if not cam_dir.is_dir():
        raise input_error(cam_dir, "missing camera folder (one <frame>.json per frame)")
    known = set(names) | (ids or set())
    try:
        entries = sorted(os.listdir(cam_dir))
    except OSError as exc:
        raise input_error(cam_dir, f"cannot be listed ({exc.strerror or exc.__class__.__name__})") from None
    for entry in entries:
        if entry.endswith(".json") and entry[:-5] not in known:
            raise input_error(
                cam_dir / entry, f"camera without a frame: {entry[:-5]} is in no split (more cameras than frames)"
            )
    cameras = []
    for name in names:
        path = cam_dir / f"{name}.json"
        if not path.exists():
            raise input_error(
                path, f"missing camera of frame {name} listed in {listed_in[name].relative_to(scene_dir)}"
            )
        cameras.append(_read_camera(path))
    W0, H0 = cameras[0]["size"]
    for name, cam in zip(names, cameras):
        if cam["size"] != (W0, H0):
            raise input_error(
                cam_dir / f"{name}.json",
                f"image_size {list(cam['size'])} differs from frame {names[0]} ({[W0, H0]}); mixed sizes are not supported",
            )
    w, h = int(round(W0 / S)), int(round(H0 / S))
    if w < 1 or h < 1:
        raise input_error(cam_dir / f"{names[0]}.json", f"image_size {[W0, H0]} is smaller than the scale factor {S}")
    K = np.stack([scale_intrinsics(c["K"], 1.0 / S) for c in cameras])
    w2c = np.stack([c["w2c"] for c in cameras])

    # Time grid.
    time_index = np.asarray(tids, dtype=np.int64)
    T = int(time_index.max()) + 1
    time = time_index / (T - 1) if T > 1 else np.zeros(F)

    # Images.
    rgb_dir = scene_dir / "rgb" / f"{S}x"
    if not rgb_dir.is_dir():
        raise input_error(
            rgb_dir, f"missing image folder for scale {S} (set the dataset option 'scale' to a scale that exists)"
        )
    images = np.empty((F, h, w, 3), np.uint8)
    alpha = np.full((F, h, w), 255, np.uint8)
    has_alpha = np.zeros(F, bool)

    def load_rgb(f: int) -> None:
        path = rgb_dir / f"{names[f]}.png"
        if not path.exists():
            raise input_error(
                path, f"missing image of frame {names[f]} listed in {listed_in[names[f]].relative_to(scene_dir)}"
            )
        try:
            img = read_image(path, expect_size=(w, h), what=f"image (camera image_size {W0}x{H0} / scale {S})")
        except cv2.error:
            raise input_error(path, "unreadable or corrupt image") from None
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        images[f] = img[..., :3]
        if img.shape[2] == 4:
            alpha[f] = img[..., 3]
            has_alpha[f] = True

    _run(load_rgb, F, workers)

    # DyCheck depth.
    depth = None
    depth_dir = scene_dir / "depth" / f"{S}x"
    if use_depth and depth_dir.is_dir():
        depth = np.zeros((F, h, w), np.float32)

        def load_depth(f: int) -> None:
            path = depth_dir / f"{names[f]}.npy"
            if not path.exists():
                if splits[f] == "train":
                    raise input_error(path, f"missing depth of train frame {names[f]} (other frames have depth)")
                return
            d = _load_npy(path, (h, w), "depth")
            if np.any(d < 0):
                raise input_error(path, "depth has negative values")
            depth[f] = d

        _run(load_depth, F, workers)

    # Covisibility (DyCheck, else SoM's copy).
    covisible = None
    for cdir in (scene_dir / "covisible" / f"{S}x" / "val", scene_dir / SOM / "covisible" / f"{S}x" / "val"):
        if cdir.is_dir() and "val" in splits:
            covisible = np.ones((F, h, w), np.uint8)

            def load_cov(f: int, cdir: Path = cdir, covisible: np.ndarray = covisible) -> None:
                if splits[f] != "val":
                    return
                path = cdir / f"{names[f]}.png"
                if not path.exists():
                    raise input_error(path, f"missing covisibility mask of val frame {names[f]}")
                covisible[f] = _binary_mask(path, (w, h), "covisibility mask")

            _run(load_cov, F, workers)
            break

    shipped: dict = {}
    meta: dict = {
        "scale": S,
        "scene_dir": str(scene_dir),
        "source_size": [int(W0), int(H0)],
        "cameras": "DyCheck camera/<frame>.json (original cameras; Shape-of-Motion's refined COLMAP cameras are not used)",
        "alpha": "DyCheck valid-pixel mask (colours not composited)" if has_alpha.any() else "none",
        "world": "camera jsons as given (not rescaled); scene_center/scene_scale map to DyCheck's normalised world: (x - center) * scale",
    }

    # Distortion: recorded, not undone.
    radial = np.stack([c["radial"] for c in cameras])
    tangential = np.stack([c["tangential"] for c in cameras])
    distorted = np.flatnonzero(np.any(radial != 0, axis=1) | np.any(tangential != 0, axis=1))
    if distorted.size:
        shipped["distortion"] = {
            "frame": distorted.astype(np.int64),
            "radial": radial[distorted],
            "tangential": tangential[distorted],
        }
        meta["distortion"] = (
            f"ignored: {distorted.size} of {F} cameras have non-zero distortion; images are used as if undistorted"
        )
        meta["max_abs_distortion"] = float(max(np.abs(radial).max(), np.abs(tangential).max()))
        warnings.warn(
            f"{cam_dir}: {distorted.size} of {F} cameras have non-zero lens distortion (max |k| {meta['max_abs_distortion']:.3g}); "
            "mogaf uses a pinhole model and does not undistort the images",
            DistortionWarning,
            stacklevel=2,
        )
    else:
        meta["distortion"] = "none"

    _scene_meta(scene_dir, meta)
    _keypoints(scene_dir, S, names, splits, time_index, shipped, h, w)

    point_cloud = None
    pts_path = scene_dir / "points.npy"
    if pts_path.exists():
        point_cloud = _points(pts_path)
        meta["point_cloud_has_color"] = False

    # Shape-of-Motion priors.
    instance_mask, instances = None, None
    if use_priors:
        mdir = scene_dir / SOM / "track_anything" / f"{S}x"
        if mdir.is_dir():
            instance_mask = np.zeros((F, h, w), np.int32)

            def load_mask(f: int) -> None:
                path = mdir / f"{names[f]}.png"
                if not path.exists():
                    raise input_error(
                        path, f"missing Shape-of-Motion foreground mask of frame {names[f]} (other frames have one)"
                    )
                instance_mask[f] = _binary_mask(path, (w, h), "foreground mask")

            _run(load_mask, F, workers)
            instances = Instances(
                ids=np.array([1]), names=["foreground"], rigid=np.array([rigidity_of("foreground", rules)])
            )
            meta["instance_mask"] = "Shape-of-Motion track_anything foreground (id 1), thresholded at 0.5"
        ddir = scene_dir / SOM / f"aligned_{som_depth}" / f"{S}x"
        if ddir.is_dir():
            rows = [f for f in range(F) if (ddir / f"{names[f]}.npy").exists()]
            if not rows:
                raise input_error(ddir, "holds no <frame>.npy disparity of any listed frame")
            values = np.zeros((len(rows), h, w), np.float32)

            def load_disp(i: int) -> None:
                values[i] = _load_npy(ddir / f"{names[rows[i]]}.npy", (h, w), "disparity")

            _run(load_disp, len(rows), workers)
            shipped["disparity"] = {"frame": np.array(rows, np.int64), "time_index": time_index[rows], "values": values}
            meta["disparity_source"] = f"{SOM}/aligned_{som_depth}/{S}x (disparity, aligned by Shape-of-Motion)"
        tdir = scene_dir / SOM / "2d_tracks" / f"{S}x"
        if use_tracks and tdir.is_dir():
            shipped["tracks_2d"] = _tracks(tdir, names, splits, time_index, q_stride, max_points, workers)
            meta["tracks_2d"] = (
                f"{SOM}/2d_tracks/{S}x, query stride {q_stride}, at most {max_points or 'all'} points per query"
            )

    out = Scene(
        dataset=dataset,
        name=scene,
        layout="iphone",
        frame_names=list(names),
        images=images,
        K=K,
        w2c=w2c,
        time=np.asarray(time, dtype=np.float64),
        time_index=time_index,
        num_timesteps=T,
        camera_id=np.asarray(cams, dtype=np.int64),
        source_split=np.array([SPLIT_CODES[s] for s in splits], dtype=np.int8),
        alpha=alpha if has_alpha.any() else None,
        instance_mask=instance_mask,
        depth=depth,
        covisible=covisible,
        instances=instances,
        point_cloud=point_cloud,
        shipped=shipped,
        meta=meta,
    )
    out.validate(scene_dir)
    return out


def _run(fn, n: int, workers: int) -> None:
    if workers <= 1 or n <= 1:
        for i in range(n):
            fn(i)
        return
    with ThreadPoolExecutor(max_workers=workers) as pool:
        list(pool.map(fn, range(n)))


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


def _points(path: Path) -> np.ndarray:
    try:
        arr = _open_npy(path)
    except (ValueError, OSError, EOFError, TypeError) as exc:
        raise input_error(path, f"unreadable or corrupt .npy points ({exc.__class__.__name__})") from None
    if not isinstance(arr, np.ndarray) or arr.ndim != 2 or arr.shape[1] not in (3, 6) or arr.dtype.kind not in "fiu":
        raise input_error(path, f"points must be an (N, 3) or (N, 6) array, got {getattr(arr, 'shape', '?')}")
    pts = np.array(arr, dtype=np.float64)
    if not np.all(np.isfinite(pts)):
        raise input_error(path, "points have non-finite values")
    if pts.shape[1] == 3:
        pts = np.concatenate([pts, np.full_like(pts, 0.5)], axis=1)
    return pts.astype(np.float32)


def _tracks(tdir: Path, names, splits, time_index, q_stride: int, max_points: int, workers: int) -> dict:
    train = [f for f in range(len(names)) if splits[f] == "train"]
    queries = train[::q_stride]
    M = len(train)
    per_query: list[np.ndarray | None] = [None] * len(queries)

    def load_query(qi: int) -> None:
        q = queries[qi]
        first = _load_tracks(tdir / f"{names[q]}_{names[q]}.npy")
        P = first.shape[0]
        keep = (
            np.arange(P)
            if not max_points or max_points >= P
            else np.unique(np.linspace(0, P - 1, max_points).round().astype(np.int64))
        )
        block = np.empty((keep.size, M, 4), np.float32)
        for j, t in enumerate(train):
            path = tdir / f"{names[q]}_{names[t]}.npy"
            arr = first if t == q else _load_tracks(path)
            if arr.shape[0] != P:
                raise input_error(path, f"has {arr.shape[0]} tracks, but query frame {names[q]} has {P}")
            try:
                vals = np.asarray(arr[keep], dtype=np.float32)
            except (ValueError, OSError) as exc:
                raise input_error(path, f"unreadable or truncated .npy tracks ({exc.__class__.__name__})") from None
            if not np.all(np.isfinite(vals)):
                raise input_error(path, "2D tracks have NaN or infinite values")
            block[:, j] = vals
        block[..., :2] += 0.5  # TAPIR/SoM pixel centres are integers; mogaf's are at +0.5
        per_query[qi] = block

    _run(load_query, len(queries), workers)
    counts = [b.shape[0] for b in per_query]
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    values = np.concatenate(per_query, axis=0) if per_query else np.zeros((0, M, 4), np.float32)
    return {
        "query_frame": np.array(queries, np.int64),
        "query_time_index": np.asarray(time_index)[queries],
        "target_frame": np.array(train, np.int64),
        "target_time_index": np.asarray(time_index)[train],
        "offsets": offsets,
        "values": values,
    }
