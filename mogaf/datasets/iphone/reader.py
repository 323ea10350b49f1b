"""The DyCheck iPhone reader: a scene folder (and Shape-of-Motion's priors
in it) -> Scene; see the package docstring for the files read."""

from __future__ import annotations

import os
import warnings
from collections.abc import Mapping
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
    outlier = camera_centre_problem(w2c)
    if outlier is not None:
        raise input_error(cam_dir / f"{names[outlier[0]]}.json", f"frame {names[outlier[0]]}: {outlier[1]}")

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
            if not instance_mask.any():
                warn_dataset(
                    mdir,
                    "every foreground mask is empty: the reconstruction has no foreground to start from; "
                    "fix the masks or remove the folder",
                )
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
