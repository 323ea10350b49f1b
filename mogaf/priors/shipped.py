"""Split-aware readers of the priors a dataset ships in scene.h5.

Only the split's observed frames are read (h5py row/column selections), so
no future frame's data is ever loaded:

- frame-indexed groups shipped/<name>/{frame (N,), values (N, ...)} for
  <name> in FRAME_INDEXED ("frame" = scene.h5 rows that have a value, e.g.
  the iPhone reader's Shape-of-Motion disparity) -> values of the observed
  frames, zeros and present = False where a frame has none;
- shipped/tracks_2d (the iPhone reader's layout of SoM's TAPIR tracks):
  query_frame (Q,), target_frame (M,), offsets (Q+1,), values
  (offsets[-1], M, 4) [x, y (+0.5 convention), occlusion logit,
  expected-distance logit] -> only queries whose query frame is observed and
  only observed target columns;
- ground_truth/{tracks2d (P, T, 2), visible (P, T)} of the synthetic scene
  -> only the observed time steps.
Everything else under shipped/ (keypoints, distortion, ...) is not read and
is reported in `ignored`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import h5py
import numpy as np

from ..artefact import open_artefact
from ..errors import input_error
from ..scene import SCENE_STAGE
from ..split import Split, load_ground_truth

FRAME_INDEXED = ("disparity", "depth", "foreground")
TRACKS = "tracks_2d"


@dataclass
class Observed:
    data: dict[str, Any] = field(default_factory=dict)
    ignored: list[str] = field(default_factory=list)


def _checked(arr: np.ndarray, path, name: str) -> np.ndarray:
    if arr.dtype.kind in "fc" and not np.all(np.isfinite(arr)):
        raise input_error(path, f"entry '{name}' contains non-finite values in the observed frames")
    return arr


def _read(ds: h5py.Dataset, sel: tuple, path) -> np.ndarray:
    try:
        return ds[sel]
    except (OSError, RuntimeError) as exc:
        raise input_error(
            path, f"entry '{ds.name}' cannot be read, file truncated or corrupted ({exc.__class__.__name__})"
        ) from None


def _frame_indexed(g: h5py.Group, rows: np.ndarray, path) -> dict[str, Any]:
    frame = np.asarray(g["frame"][()], np.int64)
    ds = g["values"]
    if ds.shape[0] != frame.size:
        raise input_error(path, f"entry '{ds.name}' has {ds.shape[0]} rows for {frame.size} frames")
    where = {int(f): i for i, f in enumerate(frame)}
    idx = np.array([where.get(int(r), -1) for r in rows], np.int64)
    present = idx >= 0
    out = np.zeros((rows.size,) + ds.shape[1:], ds.dtype)
    take = np.unique(idx[present])
    if take.size:
        block = _read(ds, (take,), path)
        out[present] = block[np.searchsorted(take, idx[present])]
    return {"values": _checked(out, path, ds.name), "present": present}


def _tracks_2d(g: h5py.Group, rows: np.ndarray, path) -> dict[str, Any]:
    query_frame = np.asarray(g["query_frame"][()], np.int64)
    target_frame = np.asarray(g["target_frame"][()], np.int64)
    offsets = np.asarray(g["offsets"][()], np.int64)
    ds = g["values"]
    if offsets.size != query_frame.size + 1 or ds.shape[1] != target_frame.size or ds.shape[0] != offsets[-1]:
        raise input_error(path, f"entry '{g.name}' is inconsistent (offsets, query/target frames, values {ds.shape})")
    col_of = {int(f): j for j, f in enumerate(target_frame)}
    cols = np.array([col_of.get(int(r), -1) for r in rows], np.int64)  # per observed frame
    have = cols >= 0
    sel_cols = np.unique(cols[have])
    pos = {int(r): i for i, r in enumerate(rows)}
    xy, occ, dist, qidx = [], [], [], []
    for q, qf in enumerate(query_frame):
        if int(qf) not in pos or offsets[q + 1] == offsets[q]:
            continue  # queried on a frame that is not observed (e.g. future): never read
        block = np.zeros((offsets[q + 1] - offsets[q], rows.size, 4), np.float32)
        block[..., 2] = 1e3  # frames without a column: occluded
        if sel_cols.size:
            vals = _read(ds, (slice(int(offsets[q]), int(offsets[q + 1])), sel_cols), path)
            block[:, have] = vals[:, np.searchsorted(sel_cols, cols[have])]
        _checked(block, path, ds.name)
        xy.append(block[..., :2])
        occ.append(block[..., 2])
        dist.append(block[..., 3])
        qidx.append(np.full(block.shape[0], pos[int(qf)], np.int64))
    if not xy:
        F = rows.size
        return {
            "xy": np.zeros((0, F, 2), np.float32),
            "occlusion": np.zeros((0, F), np.float32),
            "expected_dist": np.zeros((0, F), np.float32),
            "query_index": np.zeros(0, np.int64),
        }
    return {
        "xy": np.concatenate(xy),
        "occlusion": np.concatenate(occ),
        "expected_dist": np.concatenate(dist),
        "query_index": np.concatenate(qidx),
    }


def load_observed_shipped(scene_h5: str | os.PathLike, split: Split) -> Observed:
    """Shipped priors of the split's observed frames (see module doc)."""
    out = Observed()
    rows = np.asarray(split.frame_ids["observed"], np.int64)
    with open_artefact(scene_h5, SCENE_STAGE) as fh:
        if "shipped" not in fh:
            return out
        g = fh["shipped"]
        for name, item in g.items():
            if name in FRAME_INDEXED and isinstance(item, h5py.Group) and {"frame", "values"} <= set(item):
                out.data[name] = _frame_indexed(item, rows, scene_h5)
            elif name == TRACKS and isinstance(item, h5py.Group):
                out.data[name] = _tracks_2d(item, rows, scene_h5)
            else:
                out.ignored.append(f"shipped/{name}")
    return out


def load_observed_ground_truth_tracks(scene_h5: str | os.PathLike, split: Split) -> dict[str, Any]:
    """ground_truth/{tracks2d, visible} (train camera) at the observed steps ({} if absent)."""
    gt = load_ground_truth(scene_h5, split, "observed", entries=("tracks2d", "visible"))
    return gt if "tracks2d" in gt else {}
