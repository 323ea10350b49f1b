"""Split-aware readers of the priors a dataset ships in scene.h5.

`load_observed_shipped` reads scene.h5's `shipped/` group and
`load_observed_ground_truth_tracks` its `ground_truth/` 2D tracks, cutting
both to the observed part of the split *while reading* (h5py selections), so
no future frame's data is ever loaded:

- per-frame arrays (first axis = scene.h5 frame rows, listed in
  SHIPPED_FRAME_KEYS) -> only the split's observed rows;
- time-major arrays (a time axis over the scene's time steps, listed in
  SHIPPED_TIME_AXES) -> only the observed time steps;
- any other entry is not read (reported in `ignored`).

Shipped 2D tracks whose query time step is not observed are dropped by the
caller (their query point was picked on a future frame).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import h5py
import numpy as np

from ..artefact import open_artefact, read_rows
from ..errors import input_error
from ..scene import SCENE_STAGE
from ..split import Split

# Entries of shipped/ whose first axis is the scene.h5 frame row (leaf path
# relative to shipped/).
SHIPPED_FRAME_KEYS = {
    "depth",  # (F, H, W) float32, 0 = invalid
    "disparity",  # (F, H, W) float32, 0 = invalid
    "depth/values",
    "depth/valid",
    "disparity/values",
    "disparity/valid",
    "masks",  # (F, H, W) uint8 foreground (e.g. SoM's track_anything masks)
    "foreground",
    "masks/foreground",
}
# Entries with a time axis over the scene's time steps: leaf path -> axis.
SHIPPED_TIME_AXES = {
    "tracks2d/xy": 1,  # (P, T, 2) float32 pixel coordinates (+0.5 convention)
    "tracks2d/visible": 1,  # (P, T) uint8/bool
    "tracks2d/confidence": 1,  # (P, T) float32 (optional)
    "tracks2d/occlusion": 1,  # (P, T) float32 logits, SoM/TAPIR style (optional)
    "tracks2d/expected_dist": 1,  # (P, T) float32, SoM/TAPIR style (optional)
}
# Per-track entries (no time axis) read whole.
SHIPPED_TRACK_KEYS = {"tracks2d/query_time"}  # (P,) int64 time step of the query
# Ground-truth 2D tracks of the synthetic scene (train camera 0).
GROUND_TRUTH_TRACK_AXES = {"tracks2d": 1, "visible": 1}
GROUND_TRUTH_STATIC = {"points_instance"}


@dataclass
class Observed:
    data: dict[str, Any] = field(default_factory=dict)
    ignored: list[str] = field(default_factory=list)


def _set(tree: dict[str, Any], path: str, value: Any) -> None:
    parts = path.split("/")
    node = tree
    for p in parts[:-1]:
        node = node.setdefault(p, {})
    node[parts[-1]] = value


def _read_time_prefix(ds: h5py.Dataset, axis: int, steps: np.ndarray, num_timesteps: int, path) -> np.ndarray:
    if ds.ndim <= axis or ds.shape[axis] != num_timesteps:
        raise input_error(path, f"entry '{ds.name}' has {ds.shape} but a time axis {axis} of {num_timesteps} steps was expected")
    steps = np.asarray(steps, np.int64)
    if steps.size == 0:
        shape = list(ds.shape)
        shape[axis] = 0
        return np.zeros(shape, ds.dtype)
    sel: list[Any] = [slice(None)] * ds.ndim
    if np.array_equal(steps, np.arange(steps[0], steps[-1] + 1)):
        sel[axis] = slice(int(steps[0]), int(steps[-1]) + 1)  # contiguous: one slab
    else:
        sel[axis] = np.sort(steps)
    try:
        arr = ds[tuple(sel)]
    except (OSError, RuntimeError) as exc:
        raise input_error(path, f"entry '{ds.name}' cannot be read ({exc.__class__.__name__})") from None
    if not np.array_equal(np.sort(steps), steps):
        order = np.argsort(np.argsort(steps))
        arr = np.take(arr, order, axis=axis)
    if arr.dtype.kind in "fc" and not np.all(np.isfinite(arr)):
        raise input_error(path, f"entry '{ds.name}' contains non-finite values in the observed steps")
    return arr


def load_observed_shipped(scene_h5: str | os.PathLike, split: Split) -> Observed:
    """shipped/ entries cut to the split's observed frames and time steps."""
    out = Observed()
    rows = np.asarray(split.frame_ids["observed"], np.int64)
    with open_artefact(scene_h5, SCENE_STAGE) as fh:
        if "shipped" not in fh:
            return out
        n_frames = fh["frames/time"].shape[0]
        T = int(fh.attrs["num_timesteps"])
        items: list[tuple[str, h5py.Dataset]] = []
        fh["shipped"].visititems(lambda name, obj: items.append((name, obj)) if isinstance(obj, h5py.Dataset) else None)
        for name, ds in items:
            if name in SHIPPED_FRAME_KEYS:
                if ds.shape[0] != n_frames:
                    raise input_error(scene_h5, f"entry 'shipped/{name}' has {ds.shape[0]} rows, the scene has {n_frames} frames")
                _set(out.data, name, read_rows(fh, f"shipped/{name}", rows))
            elif name in SHIPPED_TIME_AXES:
                _set(out.data, name, _read_time_prefix(ds, SHIPPED_TIME_AXES[name], split.observed_timesteps, T, scene_h5))
            elif name in SHIPPED_TRACK_KEYS:
                _set(out.data, name, ds[()])
            else:
                out.ignored.append(f"shipped/{name}")
    return out


def load_observed_ground_truth_tracks(scene_h5: str | os.PathLike, split: Split) -> dict[str, Any]:
    """ground_truth/{tracks2d, visible, points_instance} at observed steps ({} if absent)."""
    out: dict[str, Any] = {}
    with open_artefact(scene_h5, SCENE_STAGE) as fh:
        if "ground_truth" not in fh or "tracks2d" not in fh["ground_truth"]:
            return out
        T = int(fh.attrs["num_timesteps"])
        g = fh["ground_truth"]
        for key, axis in GROUND_TRUTH_TRACK_AXES.items():
            if key in g:
                out[key] = _read_time_prefix(g[key], axis, split.observed_timesteps, T, scene_h5)
        for key in GROUND_TRUTH_STATIC:
            if key in g:
                out[key] = g[key][()]
        for key, value in g.attrs.items():
            out.setdefault("attrs", {})[key] = value
    return out
