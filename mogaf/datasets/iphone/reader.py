"""The DyCheck iPhone reader: a scene folder (and Shape-of-Motion's priors
in it) -> Scene; see the package docstring for the files read."""

from __future__ import annotations

import os
import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ...camera import camera_centre_problem, scale_intrinsics
from ...errors import MogafError, input_error
from ...scene import SPLIT_CODES, Instances, Scene
from ..common import (
    as_int,
    as_list,
    as_str,
    load_json,
    option_bool,
    option_int,
    rigidity_of,
    rigidity_rules,
    warn_dataset,
)
from ..images import read_image
from .loaders import _binary_mask, _load_npy, _points, _run, _tracks
from .metadata import _keypoints, _read_camera, _read_split, _scene_meta

SPLITS = ("train", "val")
SOM = "flow3d_preprocessed"


class DistortionWarning(UserWarning):
    """Some iPhone camera has non-zero lens distortion (images not undistorted)."""


def missing_message(scene_dir: Path, dataset: str, scene: str) -> str:
    return (
        f"{scene_dir}: DyCheck iPhone scene '{scene}' of dataset '{dataset}' not found; download DyCheck's "
        f"'{scene}' (camera/, rgb/<S>x/, depth/, covisible/, keypoint/, splits/, dataset.json, metadata.json, "
        f"scene.json, extra.json) into this folder, and unpack Shape-of-Motion's preprocessing of it "
        f"({SOM}/ with track_anything/, aligned_depth_anything_colmap/, 2d_tracks/) inside it"
    )


@dataclass
class _Options:
    scale: int
    depth: bool
    priors: bool
    tracks: bool
    query_stride: int
    max_points: int
    workers: int
    som_depth: str
    rules: list


def _read_options(options: Mapping, dataset: str) -> _Options:
    """The dataset options, each checked (in this order)."""
    where = f"dataset '{dataset}' options"
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
    return _Options(S, use_depth, use_priors, use_tracks, q_stride, max_points, workers, som_depth, rules)


@dataclass
class _Frames:
    """The frames the split files list (train then val) and, once the cameras are read, their size."""

    scene_dir: Path
    names: list[str] = field(default_factory=list)
    cams: list[int] = field(default_factory=list)
    tids: list[int] = field(default_factory=list)
    splits: list[str] = field(default_factory=list)
    listed_in: dict[str, Path] = field(default_factory=dict)
    w: int = 0
    h: int = 0

    @property
    def F(self) -> int:
        return len(self.names)

    def listed(self, name: str) -> Path:
        """The split file listing the frame, relative to the scene folder."""
        return self.listed_in[name].relative_to(self.scene_dir)


def _read_splits(scene_dir: Path, scene: str) -> _Frames:
    frames = _Frames(scene_dir)
    train_path = scene_dir / "splits" / "train.json"
    if not train_path.exists():
        raise input_error(train_path, f"missing (the DyCheck train split of scene '{scene}')")
    for split in SPLITS:
        path = scene_dir / "splits" / f"{split}.json"
        if split != "train" and not path.exists():
            continue
        n, c, t = _read_split(path)
        for name in n:
            if name in frames.listed_in:
                raise input_error(path, f"frame {name} is listed twice (also in {frames.listed_in[name].name})")
            frames.listed_in[name] = path
        frames.names += n
        frames.cams += c
        frames.tids += t
        frames.splits += [split] * len(n)
    if not frames.names:
        raise input_error(train_path, "lists no frames")
    return frames


def _dataset_ids(scene_dir: Path, frames: _Frames) -> set[str] | None:
    """The ids of dataset.json (None without the file or its 'ids'), each listed frame among them."""
    dpath = scene_dir / "dataset.json"
    if not dpath.exists():
        return None
    dd = load_json(dpath, what="DyCheck dataset")
    if "ids" not in dd:
        return None
    id_list = [as_str(x, dpath, f"ids[{i}]") for i, x in enumerate(as_list(dd["ids"], dpath, "'ids'"))]
    ids = set(id_list)
    if "count" in dd and as_int(dd["count"], dpath, "count", lo=0) != len(id_list):
        raise input_error(dpath, f"count is {dd['count']} but ids lists {len(id_list)} frames")
    for name in frames.names:
        if name not in ids:
            raise input_error(frames.listed_in[name], f"frame {name} is not among the ids of dataset.json")
    return ids


def _check_metadata(scene_dir: Path, frames: _Frames) -> None:
    """metadata.json, where present, agrees with the splits on every frame's camera and time."""
    mpath = scene_dir / "metadata.json"
    if not mpath.exists():
        return
    md = load_json(mpath, what="DyCheck metadata")
    for name, cam, t in zip(frames.names, frames.cams, frames.tids):
        split_name = frames.listed_in[name].name
        if name not in md:
            raise input_error(mpath, f"has no entry for frame {name} (listed in {split_name})")
        entry = md[name]
        if not isinstance(entry, dict):
            raise input_error(mpath, f"entry {name} must be an object")
        if "camera_id" in entry and as_int(entry["camera_id"], mpath, f"{name} camera_id") != cam:
            raise input_error(mpath, f"frame {name}: camera_id {entry['camera_id']} differs from {split_name} ({cam})")
        if "warp_id" in entry and as_int(entry["warp_id"], mpath, f"{name} warp_id") != t:
            raise input_error(
                mpath, f"frame {name}: warp_id {entry['warp_id']} differs from the time_id in {split_name} ({t})"
            )


def _read_cameras(cam_dir: Path, frames: _Frames, ids: set[str] | None) -> list[dict]:
    """One camera per listed frame, none left over."""
    if not cam_dir.is_dir():
        raise input_error(cam_dir, "missing camera folder (one <frame>.json per frame)")
    known = set(frames.names) | (ids or set())
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
    for name in frames.names:
        path = cam_dir / f"{name}.json"
        if not path.exists():
            raise input_error(path, f"missing camera of frame {name} listed in {frames.listed(name)}")
        cameras.append(_read_camera(path))
    return cameras


def _source_size(cam_dir: Path, names: list[str], cameras: list[dict], S: int) -> tuple[int, int]:
    """The cameras' one image size (W, H), at least the scale factor."""
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
    return W0, H0


def _load_images(frames: _Frames, S: int, source_size: tuple[int, int], workers: int):
    """(images, alpha, has_alpha) of rgb/<S>x."""
    names, w, h = frames.names, frames.w, frames.h
    rgb_dir = frames.scene_dir / "rgb" / f"{S}x"
    if not rgb_dir.is_dir():
        raise input_error(
            rgb_dir, f"missing image folder for scale {S} (set the dataset option 'scale' to a scale that exists)"
        )
    images = np.empty((frames.F, h, w, 3), np.uint8)
    alpha = np.full((frames.F, h, w), 255, np.uint8)
    has_alpha = np.zeros(frames.F, bool)
    what = f"image (camera image_size {source_size[0]}x{source_size[1]} / scale {S})"

    def load_rgb(f: int) -> None:
        path = rgb_dir / f"{names[f]}.png"
        if not path.exists():
            raise input_error(path, f"missing image of frame {names[f]} listed in {frames.listed(names[f])}")
        try:
            img = read_image(path, expect_size=(w, h), what=what)
        except cv2.error:
            raise input_error(path, "unreadable or corrupt image") from None
        if img.ndim == 2:
            img = np.repeat(img[..., None], 3, axis=2)
        images[f] = img[..., :3]
        if img.shape[2] == 4:
            alpha[f] = img[..., 3]
            has_alpha[f] = True

    _run(load_rgb, frames.F, workers)
    return images, alpha, has_alpha


def _load_depth(frames: _Frames, S: int, workers: int) -> np.ndarray | None:
    """DyCheck's depth/<S>x, None without the folder; every train frame has one."""
    names, splits = frames.names, frames.splits
    depth_dir = frames.scene_dir / "depth" / f"{S}x"
    if not depth_dir.is_dir():
        return None
    depth = np.zeros((frames.F, frames.h, frames.w), np.float32)

    def load_depth(f: int) -> None:
        path = depth_dir / f"{names[f]}.npy"
        if not path.exists():
            if splits[f] == "train":
                raise input_error(path, f"missing depth of train frame {names[f]} (other frames have depth)")
            return
        d = _load_npy(path, (frames.h, frames.w), "depth")
        if np.any(d < 0):
            raise input_error(path, "depth has negative values")
        depth[f] = d

    _run(load_depth, frames.F, workers)
    return depth


def _load_covisible(frames: _Frames, S: int, workers: int) -> np.ndarray | None:
    """Covisibility masks of the val frames (DyCheck's, else SoM's copy), None without either folder."""
    names, splits = frames.names, frames.splits
    scene_dir = frames.scene_dir
    if "val" not in splits:
        return None
    for cdir in (scene_dir / "covisible" / f"{S}x" / "val", scene_dir / SOM / "covisible" / f"{S}x" / "val"):
        if not cdir.is_dir():
            continue
        covisible = np.ones((frames.F, frames.h, frames.w), np.uint8)

        def load_cov(f: int, cdir: Path = cdir, covisible: np.ndarray = covisible) -> None:
            if splits[f] != "val":
                return
            path = cdir / f"{names[f]}.png"
            if not path.exists():
                raise input_error(path, f"missing covisibility mask of val frame {names[f]}")
            covisible[f] = _binary_mask(path, (frames.w, frames.h), "covisibility mask")

        _run(load_cov, frames.F, workers)
        return covisible
    return None


def _record_distortion(cam_dir: Path, cameras: list[dict], shipped: dict, meta: dict) -> None:
    """Distortion: recorded in shipped and meta (and warned about), not undone."""
    F = len(cameras)
    radial = np.stack([c["radial"] for c in cameras])
    tangential = np.stack([c["tangential"] for c in cameras])
    distorted = np.flatnonzero(np.any(radial != 0, axis=1) | np.any(tangential != 0, axis=1))
    if not distorted.size:
        meta["distortion"] = "none"
        return
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
        stacklevel=3,  # the caller of read_iphone_layout
    )


def _load_foreground(frames: _Frames, S: int, opts: _Options, meta: dict):
    """(instance_mask, instances) of Shape-of-Motion's track_anything foreground; (None, None) without it."""
    names = frames.names
    mdir = frames.scene_dir / SOM / "track_anything" / f"{S}x"
    if not mdir.is_dir():
        return None, None
    instance_mask = np.zeros((frames.F, frames.h, frames.w), np.int32)

    def load_mask(f: int) -> None:
        path = mdir / f"{names[f]}.png"
        if not path.exists():
            raise input_error(
                path, f"missing Shape-of-Motion foreground mask of frame {names[f]} (other frames have one)"
            )
        instance_mask[f] = _binary_mask(path, (frames.w, frames.h), "foreground mask")

    _run(load_mask, frames.F, opts.workers)
    instances = Instances(
        ids=np.array([1]), names=["foreground"], rigid=np.array([rigidity_of("foreground", opts.rules)])
    )
    meta["instance_mask"] = "Shape-of-Motion track_anything foreground (id 1), thresholded at 0.5"
    return instance_mask, instances


def _load_disparity(frames: _Frames, S: int, opts: _Options, time_index: np.ndarray, shipped: dict, meta: dict) -> None:
    """Shape-of-Motion's aligned disparity of the frames that have one, into shipped."""
    names, som_depth = frames.names, opts.som_depth
    ddir = frames.scene_dir / SOM / f"aligned_{som_depth}" / f"{S}x"
    if not ddir.is_dir():
        return
    rows = [f for f in range(frames.F) if (ddir / f"{names[f]}.npy").exists()]
    if not rows:
        raise input_error(ddir, "holds no <frame>.npy disparity of any listed frame")
    values = np.zeros((len(rows), frames.h, frames.w), np.float32)

    def load_disp(i: int) -> None:
        values[i] = _load_npy(ddir / f"{names[rows[i]]}.npy", (frames.h, frames.w), "disparity")

    _run(load_disp, len(rows), opts.workers)
    source = f"{SOM}/aligned_{som_depth}/{S}x (disparity, aligned by Shape-of-Motion)"
    if som_depth.endswith("_colmap"):
        # Aligned to Shape-of-Motion's COLMAP reconstruction, whose unit is not the camera jsons':
        # lengths there times colmap/scale.npy are the jsons' (its evaluate_iphone.py scales so).
        scale = _colmap_scale(frames.scene_dir / SOM / "colmap" / "scale.npy", ddir)
        values /= np.float32(scale)
        source += f", divided by {SOM}/colmap/scale.npy ({scale:g}) to the camera jsons' units"
    shipped["disparity"] = {"frame": np.array(rows, np.int64), "time_index": time_index[rows], "values": values}
    meta["disparity_source"] = source


def _colmap_scale(path: Path, disparity_dir: Path) -> float:
    """Shape-of-Motion's COLMAP-to-camera-json length factor: one finite positive number."""
    if not path.is_file():
        raise input_error(
            disparity_dir,
            f"is aligned to Shape-of-Motion's COLMAP reconstruction, whose unit needs {path} "
            "(Shape-of-Motion's iPhone scenes ship it); or name a disparity in the camera jsons' units "
            "with the dataset option som_depth",
        )
    try:
        value = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise input_error(path, f"cannot be read as a .npy array ({exc})") from None
    numeric = np.issubdtype(np.asarray(value).dtype, np.number)
    if not numeric or np.size(value) != 1 or not np.isfinite(value).all() or float(np.ravel(value)[0]) <= 0:
        raise input_error(path, f"must hold one finite positive number, holds {np.ravel(value)[:3]!r}")
    return float(np.ravel(value)[0])


def _load_tracks(frames: _Frames, S: int, opts: _Options, time_index: np.ndarray, shipped: dict, meta: dict) -> None:
    """Shape-of-Motion's 2D tracks (unless the option `tracks` is off), into shipped."""
    tdir = frames.scene_dir / SOM / "2d_tracks" / f"{S}x"
    if not (opts.tracks and tdir.is_dir()):
        return
    q_stride, max_points = opts.query_stride, opts.max_points
    shipped["tracks_2d"] = _tracks(tdir, frames.names, frames.splits, time_index, q_stride, max_points, opts.workers)
    meta["tracks_2d"] = f"{SOM}/2d_tracks/{S}x, query stride {q_stride}, at most {max_points or 'all'} points per query"


def read_iphone_layout(scene_dir: str | os.PathLike, dataset: str, scene: str, options: Mapping | None = None) -> Scene:
    """Read a DyCheck iPhone scene folder (and SoM priors in it) into a Scene."""
    scene_dir = Path(scene_dir)
    options = dict(options or {})
    if not scene_dir.is_dir():
        raise MogafError(missing_message(scene_dir, dataset, scene))
    opts = _read_options(options, dataset)
    S = opts.scale

    frames = _read_splits(scene_dir, scene)
    names, splits, F = frames.names, frames.splits, frames.F
    # Optional cross-checks with dataset.json / metadata.json.
    ids = _dataset_ids(scene_dir, frames)
    _check_metadata(scene_dir, frames)

    cam_dir = scene_dir / "camera"
    cameras = _read_cameras(cam_dir, frames, ids)
    W0, H0 = _source_size(cam_dir, names, cameras, S)
    frames.w, frames.h = int(round(W0 / S)), int(round(H0 / S))
    K = np.stack([scale_intrinsics(c["K"], 1.0 / S) for c in cameras])
    w2c = np.stack([c["w2c"] for c in cameras])
    outlier = camera_centre_problem(w2c)
    if outlier is not None:
        raise input_error(cam_dir / f"{names[outlier[0]]}.json", f"frame {names[outlier[0]]}: {outlier[1]}")

    # Time grid.
    time_index = np.asarray(frames.tids, dtype=np.int64)
    T = int(time_index.max()) + 1
    time = time_index / (T - 1) if T > 1 else np.zeros(F)

    images, alpha, has_alpha = _load_images(frames, S, (W0, H0), opts.workers)
    depth = _load_depth(frames, S, opts.workers) if opts.depth else None
    covisible = _load_covisible(frames, S, opts.workers)

    shipped: dict = {}
    meta: dict = {
        "scale": S,
        "scene_dir": str(scene_dir),
        "source_size": [int(W0), int(H0)],
        "cameras": "DyCheck camera/<frame>.json (original cameras; Shape-of-Motion's refined COLMAP cameras are not used)",
        "alpha": "DyCheck valid-pixel mask (colours not composited)" if has_alpha.any() else "none",
        "world": "camera jsons as given (not rescaled); scene_center/scene_scale map to DyCheck's normalised world: (x - center) * scale",
    }
    _record_distortion(cam_dir, cameras, shipped, meta)
    _scene_meta(scene_dir, meta)
    _keypoints(scene_dir, S, names, splits, time_index, shipped, frames.h, frames.w)

    point_cloud = None
    pts_path = scene_dir / "points.npy"
    if pts_path.exists():
        point_cloud = _points(pts_path)
        meta["point_cloud_has_color"] = False

    # Shape-of-Motion priors: its foreground mask, aligned disparity and 2D tracks.
    instance_mask, instances = None, None
    if opts.priors:
        instance_mask, instances = _load_foreground(frames, S, opts, meta)
        if instance_mask is not None and not instance_mask.any():
            warn_dataset(
                scene_dir / SOM / "track_anything" / f"{S}x",
                "every foreground mask is empty: the reconstruction has no foreground to start from; "
                "fix the masks or remove the folder",
            )
        _load_disparity(frames, S, opts, time_index, shipped, meta)
        _load_tracks(frames, S, opts, time_index, shipped, meta)

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
        camera_id=np.asarray(frames.cams, dtype=np.int64),
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
