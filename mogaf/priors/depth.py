"""Depth prior of monocular (layout "iphone") scenes.

Sources, in the order of `depth_sources`:
- "shipped": scene.h5 shipped/depth or shipped/disparity (for example
  Shape-of-Motion's aligned Depth-Anything disparity), per observed frame
  (frames without a shipped map are invalid);
- "scene": the scene's own depth (DyCheck lidar depth, synthetic GT depth).
Values are kept as shipped; `depth_kind` says whether they are depth or
disparity. valid = value > 0 (and the shipped valid mask when there is one).
No monocular depth estimator runs here: a scene with neither fails with one
line naming the files to provide.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

import cv2
import numpy as np

from ..errors import MogafError, input_error

DEPTH_SOURCES = ("shipped", "scene")


def _as_hw(arr: np.ndarray, H: int, W: int, interp: int) -> np.ndarray:
    if arr.shape[1:3] == (H, W):
        return arr
    return np.stack([cv2.resize(a, (W, H), interpolation=interp) for a in arr])


def _shipped_depth(shipped: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray | None, str] | None:
    for kind in ("depth", "disparity"):
        entry = shipped.get(kind)
        if isinstance(entry, Mapping) and "values" in entry:
            return np.asarray(entry["values"]), entry.get("present"), kind
    return None


def missing_depth_message(scene_h5: str | os.PathLike, meta: Mapping[str, Any], name: str) -> str:
    where = meta.get("scene_dir") or meta.get("source_dir") or meta.get("data_dir") or "<scene_dir>"
    factor = meta.get("scale") or meta.get("downscale") or meta.get("factor") or "<S>"
    return (
        f"monocular scene '{name}' has no depth prior: provide {where}/depth/{factor}x/<frame>.npy (metric depth) "
        f"or {where}/flow3d_preprocessed/aligned_depth_anything_colmap/{factor}x/<frame>.npy "
        f"(Shape-of-Motion's aligned disparity), then re-run ingest"
    )


def select_depth(
    scene_h5: str | os.PathLike, scene, shipped: Mapping[str, Any], order: Sequence[str]
) -> tuple[np.ndarray, np.ndarray, str, str]:
    """(values (F,H,W) float32, valid (F,H,W) uint8, depth_kind, source)."""
    F, H, W = scene.num_frames, scene.height, scene.width
    for src in order:
        if src not in DEPTH_SOURCES:
            raise MogafError(f"priors: depth source {src!r} is not one of {DEPTH_SOURCES}")
        if src == "shipped":
            got = _shipped_depth(shipped)
            if got is None:
                continue
            values, valid, kind = got
            name = f"shipped/{kind}"
        else:
            if scene.depth is None:
                continue
            values, valid, kind, name = scene.depth, None, "depth", "scene_depth"
        values = np.asarray(values, np.float32)
        if values.ndim == 4 and values.shape[-1] == 1:
            values = values[..., 0]
        if values.ndim != 3 or values.shape[0] != F:
            raise input_error(scene_h5, f"{name} has shape {values.shape}, expected ({F}, {H}, {W})")
        values = _as_hw(values, H, W, cv2.INTER_NEAREST)
        ok = np.isfinite(values) & (values > 0)
        if valid is not None:
            valid = np.asarray(valid).astype(bool)
            ok &= valid.reshape(valid.shape + (1,) * (3 - valid.ndim))  # per-frame "present" flags
        values = np.where(ok, values, 0.0).astype(np.float32)
        return values, ok.astype(np.uint8), kind, name
    raise input_error(scene_h5, missing_depth_message(scene_h5, scene.meta, scene.name))
