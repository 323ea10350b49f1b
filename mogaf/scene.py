"""One in-memory scene model for every dataset layout, and scene.h5.

Arrays are stored frame-major ("struct of arrays"): frame f has image
images[f], intrinsics K[f], world-to-camera w2c[f] (OpenCV), normalised time
time[f] in [0, 1], integer time_index[f] on the scene's uniform time grid
(0 .. num_timesteps-1), camera_id[f] and the dataset split it came from.

Optional per-frame arrays (None when the dataset has none): alpha, instance
masks (0 = background, ids listed in `instances`), depth (0 = invalid) and
covisibility masks. Dataset-shipped priors (for example Shape-of-Motion 2D
tracks or aligned disparity) and ground truth (the synthetic scene's 3D
trajectories) live in `shipped` and `ground_truth`; later stages read them
only through the split (see mogaf.split).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .artefact import _decode_attr, open_artefact, read_rows, read_tree, write_artefact
from .camera import camera_centre_problem, pose_problem
from .errors import MogafError, input_error

SCENE_STAGE = "ingest"
SPLIT_CODES = {"train": 0, "val": 1, "test": 2}
SPLIT_NAMES = {v: k for k, v in SPLIT_CODES.items()}
LAYOUTS = ("iphone", "dnerf")
MAX_TIMESTEPS = 1 << 24  # far beyond any video; bounds what a reader allocates per time step

# Per-frame arrays stored under /frames, in the order they are checked.
FRAME_ARRAYS = ("images", "K", "w2c", "time", "time_index", "camera_id", "source_split")
OPTIONAL_FRAME_ARRAYS = ("alpha", "instance_mask", "depth", "covisible")


@dataclass
class Instances:
    """Object identities present in instance masks (id 0 is background)."""

    ids: np.ndarray  # (K,) int
    names: list[str]
    # 1 rigid, 0 non-rigid, -1 unknown (decided later from motion).
    rigid: np.ndarray  # (K,) int8

    def __post_init__(self) -> None:
        self.ids = np.asarray(self.ids, dtype=np.int64)
        self.rigid = np.asarray(self.rigid, dtype=np.int8)
        if not (len(self.ids) == len(self.names) == len(self.rigid)):
            raise MogafError("instances: ids, names and rigid flags differ in length")


@dataclass
class Segments:
    """Ground-truth pieces that each move as one, for scoring a grouping only
    (no stage that fits or groups reads them): label[f] is 0 on background and
    s in 1..S on segment s, a part of instance[s - 1] called names[s - 1]."""

    label: np.ndarray  # (F, H, W) uint16
    instance: np.ndarray  # (S,) int64
    names: list[str]

    def __post_init__(self) -> None:
        self.instance = np.asarray(self.instance, dtype=np.int64)
        if len(self.instance) != len(self.names):
            raise MogafError("segments: instance ids and names differ in length")

    def label_problem(self) -> str | None:
        """A label naming no segment, or None."""
        top = int(self.label.max()) if self.label.size else 0
        if top > len(self.names):
            return f"segment labels go up to {top}, but {len(self.names)} segments are named"
        return None


@dataclass
class Scene:
    dataset: str
    name: str
    layout: str  # "iphone" (monocular video + held-out cameras) or "dnerf"
    frame_names: list[str]
    images: np.ndarray  # (F, H, W, 3) uint8
    K: np.ndarray  # (F, 3, 3) float64
    w2c: np.ndarray  # (F, 4, 4) float64, OpenCV world-to-camera
    time: np.ndarray  # (F,) float64 in [0, 1]
    time_index: np.ndarray  # (F,) int64 in [0, num_timesteps)
    num_timesteps: int
    camera_id: np.ndarray  # (F,) int64
    source_split: np.ndarray  # (F,) int8, SPLIT_CODES
    alpha: np.ndarray | None = None  # (F, H, W) uint8
    instance_mask: np.ndarray | None = None  # (F, H, W) int32
    depth: np.ndarray | None = None  # (F, H, W) float32, 0 = invalid
    covisible: np.ndarray | None = None  # (F, H, W) uint8 (1 = covisible)
    instances: Instances | None = None
    point_cloud: np.ndarray | None = None  # (P, 6) float32: xyz, rgb in [0, 1]
    shipped: dict[str, Any] = field(default_factory=dict)
    ground_truth: dict[str, Any] = field(default_factory=dict)
    segments: Segments | None = None
    # Scalars: background colour, scene scale, fps, monocular flag, ...
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def num_frames(self) -> int:
        return int(self.images.shape[0])

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    def covisibility_masks(self) -> np.ndarray | None:
        """(F, H, W) float32, 1 where the pixel is co-visible (the masked
        metrics' masks), or None where the scene has none."""
        if self.covisible is None:
            return None
        return (np.asarray(self.covisible) > 0).astype(np.float32)

    def validate(self, source: str | os.PathLike) -> None:
        """Raise a one-line MogafError naming `source` if the scene is inconsistent."""
        problem = (
            self._layout_problem()
            or self._values_problem()
            or self._cameras_problem()
            or self._optional_arrays_problem()
        )
        if problem:
            raise input_error(source, problem)

    def _layout_problem(self) -> str | None:
        """The layout, and the type and shape of every per-frame array."""
        F = self.num_frames
        if self.layout not in LAYOUTS:
            return f"unknown layout '{self.layout}'"
        if F == 0:
            return "scene has no frames"
        if self.images.ndim != 4 or self.images.shape[-1] != 3 or self.images.dtype != np.uint8:
            return f"images must be (F, H, W, 3) uint8, got {self.images.shape} {self.images.dtype}"
        expect = {
            "K": (F, 3, 3),
            "w2c": (F, 4, 4),
            "time": (F,),
            "time_index": (F,),
            "camera_id": (F,),
            "source_split": (F,),
        }
        for key, shape in expect.items():
            arr = getattr(self, key)
            if arr.shape != shape:
                return f"{key} has shape {arr.shape}, expected {shape} (one per frame)"
        if len(self.frame_names) != F:
            return f"{len(self.frame_names)} frame names for {F} frames"
        return None

    def _values_problem(self) -> str | None:
        """Finite cameras and times, times and time indices in range, positive focal lengths."""
        for key in ("K", "w2c", "time"):
            if not np.all(np.isfinite(getattr(self, key))):
                return f"{key} has non-finite values"
        if np.any(self.time < 0) or np.any(self.time > 1):
            return "frame times must lie in [0, 1]"
        if self.num_timesteps < 1 or np.any(self.time_index < 0) or np.any(self.time_index >= self.num_timesteps):
            return f"time_index must lie in [0, {self.num_timesteps})"
        if np.any(self.K[:, 0, 0] <= 0) or np.any(self.K[:, 1, 1] <= 0):
            return "focal lengths must be positive"
        return None

    def _cameras_problem(self) -> str | None:
        """Rigid camera poses, no camera far off the others."""
        for f in range(self.num_frames):
            problem = pose_problem(self.w2c[f])
            if problem:
                return f"frame {self.frame_names[f]}: {problem}"
        outlier = camera_centre_problem(self.w2c)
        if outlier is not None:
            return f"frame {self.frame_names[outlier[0]]}: {outlier[1]}"
        return None

    def _optional_arrays_problem(self) -> str | None:
        """The optional per-frame arrays' shapes, and finite, non-negative depth."""
        F, H, W = self.num_frames, self.height, self.width
        for key in OPTIONAL_FRAME_ARRAYS:
            arr = getattr(self, key)
            if arr is not None and arr.shape[:3] != (F, H, W):
                return f"{key} has shape {arr.shape}, expected ({F}, {H}, {W})"
        if self.segments is not None:
            label = self.segments.label
            if label.shape != (F, H, W):
                return f"segment labels have shape {label.shape}, expected ({F}, {H}, {W})"
            problem = self.segments.label_problem()
            if problem:
                return problem
        if self.depth is not None:
            if not np.all(np.isfinite(self.depth)):
                return "depth has NaN or infinite values"
            if np.any(self.depth < 0):
                return "depth has negative values"
        return None


def _scene_payload(scene: Scene) -> tuple[dict[str, Any], dict[str, Any]]:
    frames = {key: getattr(scene, key) for key in FRAME_ARRAYS}
    frames["names"] = list(scene.frame_names)
    for key in OPTIONAL_FRAME_ARRAYS:
        if getattr(scene, key) is not None:
            frames[key] = getattr(scene, key)
    data: dict[str, Any] = {"frames": frames}
    if scene.instances is not None:
        data["instances"] = {
            "ids": scene.instances.ids,
            "names": list(scene.instances.names),
            "rigid": scene.instances.rigid,
        }
    if scene.point_cloud is not None:
        data["point_cloud"] = np.asarray(scene.point_cloud, dtype=np.float32)
    if scene.shipped:
        data["shipped"] = scene.shipped
    if scene.ground_truth:
        data["ground_truth"] = scene.ground_truth
    if scene.segments is not None:
        data["segments"] = {
            "label": np.asarray(scene.segments.label, dtype=np.uint16),
            "instance": scene.segments.instance,
            "names": list(scene.segments.names),
        }
    attrs = {
        "dataset": scene.dataset,
        "scene": scene.name,
        "layout": scene.layout,
        "num_timesteps": int(scene.num_timesteps),
        "height": scene.height,
        "width": scene.width,
        "meta": scene.meta,
    }
    return data, attrs


def save_scene(path: str | os.PathLike, scene: Scene, *, config_digest: str) -> Path:
    scene.validate(path)
    data, attrs = _scene_payload(scene)
    return write_artefact(path, SCENE_STAGE, data, config_digest=config_digest, attrs=attrs)


def check_scene_file(fh, path: str | os.PathLike) -> tuple[int, int]:
    """scene.h5's attributes and per-frame entry shapes, from its metadata
    alone (nothing read): one line naming the file where a reader would
    otherwise fail later, far from it. Returns (frames, time steps)."""
    T = _decode_attr(fh.attrs.get("num_timesteps"))
    if isinstance(T, bool) or not isinstance(T, int) or not 1 <= T <= MAX_TIMESTEPS:
        raise input_error(
            path, f"attribute num_timesteps is {T!r}; it must be an integer in [1, {MAX_TIMESTEPS}] (rerun ingest)"
        )
    layout = _decode_attr(fh.attrs.get("layout"))
    if not isinstance(layout, str) or layout not in LAYOUTS:
        raise input_error(path, f"attribute layout is {layout!r}; expected one of {', '.join(LAYOUTS)} (rerun ingest)")
    for key in (*FRAME_ARRAYS, "names"):
        if f"frames/{key}" not in fh:
            raise input_error(path, f"has no entry 'frames/{key}' (rerun ingest)")
    images = fh["frames/images"].shape
    if len(images) != 4 or images[-1] != 3:
        raise input_error(path, f"entry 'frames/images' has shape {images}, expected (frames, height, width, 3)")
    F, H, W = images[:3]
    expect = {
        "K": (F, 3, 3),
        "w2c": (F, 4, 4),
        "time": (F,),
        "time_index": (F,),
        "camera_id": (F,),
        "source_split": (F,),
        "names": (F,),
    }
    for key, shape in expect.items():
        if fh[f"frames/{key}"].shape != shape:
            raise input_error(
                path,
                f"entry 'frames/{key}' has shape {fh[f'frames/{key}'].shape}, expected {shape} "
                f"(one per frame; {F} frames)",
            )
    for key, kinds in (("time", "f"), ("time_index", "iu"), ("camera_id", "iu")):
        if fh[f"frames/{key}"].dtype.kind not in kinds:
            raise input_error(
                path, f"entry 'frames/{key}' holds {fh[f'frames/{key}'].dtype}, not numbers (rerun ingest)"
            )
    for key in OPTIONAL_FRAME_ARRAYS:
        if f"frames/{key}" in fh and fh[f"frames/{key}"].shape[:3] != (F, H, W):
            raise input_error(
                path, f"entry 'frames/{key}' has shape {fh[f'frames/{key}'].shape}, expected ({F}, {H}, {W}, ...)"
            )
    return int(F), int(T)


def _read_group(fh, key: str) -> dict[str, Any]:
    return read_tree(fh[key], Path(fh.filename), prefix=f"{key}/") if key in fh else {}


def load_scene(
    path: str | os.PathLike,
    frames: np.ndarray | None = None,
    *,
    with_ground_truth: bool = False,
    with_shipped: bool = False,
) -> Scene:
    """Load scene.h5, optionally only the frames listed in `frames`.

    Stages after `split` must pass the frame ids their split gives them (see
    mogaf.split.load_frames); only those rows are returned (the reader
    decompresses whole HDF5 chunks, which may hold other frames' rows, and
    discards those rows before anything else sees them).
    """
    p = Path(path)
    with open_artefact(p, SCENE_STAGE) as fh:
        total, _ = check_scene_file(fh, p)
        attrs = {k: _decode_attr(v) for k, v in fh.attrs.items()}
        rows = np.arange(total) if frames is None else np.asarray(frames, dtype=np.int64)
        arrays = {key: read_rows(fh, f"frames/{key}", rows) for key in FRAME_ARRAYS}
        optional = {
            key: (read_rows(fh, f"frames/{key}", rows) if f"frames/{key}" in fh else None)
            for key in OPTIONAL_FRAME_ARRAYS
        }
        names_all = fh["frames/names"].asstr()[()]
        names = [str(names_all[i]) for i in rows]
        instances = None
        if "instances" in fh:
            g = _read_group(fh, "instances")
            instances = Instances(ids=g["ids"], names=list(g["names"]), rigid=g["rigid"])
        point_cloud = (
            read_rows(fh, "point_cloud", np.arange(fh["point_cloud"].shape[0])) if "point_cloud" in fh else None
        )
        shipped = _read_group(fh, "shipped") if with_shipped else {}
        ground_truth = _read_group(fh, "ground_truth") if with_ground_truth else {}
    return Scene(
        dataset=attrs["dataset"],
        name=attrs["scene"],
        layout=attrs["layout"],
        frame_names=names,
        num_timesteps=int(attrs["num_timesteps"]),
        instances=instances,
        point_cloud=point_cloud,
        shipped=shipped,
        ground_truth=ground_truth,
        meta=dict(attrs.get("meta") or {}),
        **arrays,
        **optional,
    )


def load_segments(path: str | os.PathLike, frames: np.ndarray) -> Segments | None:
    """The ground-truth segments of the listed frames (None where scene.h5 has
    none). For scoring only: the grouping quality stage, never a fitting one."""
    p = Path(path)
    with open_artefact(p, SCENE_STAGE) as fh:
        total, _ = check_scene_file(fh, p)
        if "segments" not in fh:
            return None
        for key in ("label", "instance", "names"):
            if f"segments/{key}" not in fh:
                raise input_error(p, f"has no entry 'segments/{key}' (rerun ingest)")
        if fh["segments/label"].shape[0] != total:
            raise input_error(
                p, f"entry 'segments/label' has {fh['segments/label'].shape[0]} rows for {total} frames (rerun ingest)"
            )
        label = read_rows(fh, "segments/label", np.asarray(frames, dtype=np.int64))
        instance = read_rows(fh, "segments/instance", np.arange(fh["segments/instance"].shape[0]))
        names = [str(n) for n in fh["segments/names"].asstr()[()]]
    if len(names) != len(instance):
        raise input_error(
            p, f"entries 'segments/*' disagree: {len(instance)} instance ids, {len(names)} names (rerun ingest)"
        )
    segments = Segments(label=label, instance=instance, names=names)
    problem = segments.label_problem()
    if problem:
        raise input_error(p, f"{problem} (rerun ingest)")
    return segments
