"""2D tracks read from files (shipped, synthetic ground truth) and their frame order.

Shipped tracks (Shape-of-Motion/TAPIR) and the synthetic scene's ground-truth
tracks become Tracks over the observed frames: invisible steps filled with
the last known position, tracks shorter than `min_track_length` dropped, a
seeded subsample above `max_tracks`. _composite_tracks maps tracks computed
in temporal order back to the split's frame order.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from scipy.special import expit

from ..split import Split
from .tracks import Tracks


def _finish_tracks(
    xy: np.ndarray, vis: np.ndarray, conf: np.ndarray | None, query_index: np.ndarray | None, p: Mapping[str, Any]
) -> Tracks:
    """Tracks over the observed frames from file data: fill, filter, cap."""
    P, F = vis.shape
    keep = vis.sum(1) >= int(p.min_track_length)
    if query_index is None:
        query_index = np.where(vis.any(1), vis.argmax(1), 0).astype(np.int64)
    xy = _fill_invisible(np.asarray(xy, np.float32), vis)
    conf = vis.astype(np.float32) if conf is None else np.asarray(conf, np.float32)
    conf = np.where(vis, np.clip(conf, 0.0, 1.0), 0.0).astype(np.float32)
    tr = Tracks(
        query_index=np.asarray(query_index, np.int64), xy=xy, visible=vis, confidence=conf, fb_error=None
    ).subset(keep)
    cap = int(p.max_tracks)
    if cap > 0 and tr.num_tracks > cap:
        rng = np.random.default_rng(int(p.seed))
        tr = tr.subset(np.sort(rng.choice(tr.num_tracks, cap, replace=False)))
    return tr


def _fill_invisible(xy: np.ndarray, vis: np.ndarray) -> np.ndarray:
    P, F = vis.shape
    out = np.where(np.isfinite(xy), xy, 0.0).astype(np.float32)
    if P == 0 or F == 0:
        return out
    idx = np.where(vis, np.arange(F)[None], -1)
    last = np.maximum.accumulate(idx, axis=1)  # last visible frame at or before t
    first = np.where(vis.any(1), vis.argmax(1), 0)
    src = np.where(last >= 0, last, first[:, None])
    return np.take_along_axis(out, src[..., None].repeat(2, -1), axis=1)


def _shipped_tracks(shipped: Mapping[str, Any], p) -> Tracks | None:
    """Shape-of-Motion/TAPIR tracks: visible where (1 - sigmoid(occlusion)) *
    (1 - sigmoid(expected_dist)) > 0.5, as SoM reads them; confidence =
    1 - sigmoid(expected_dist)."""
    g = shipped.get("tracks_2d")
    if not isinstance(g, Mapping) or "xy" not in g:
        return None
    visibility = expit(-np.asarray(g["occlusion"], np.float64))
    certainty = expit(-np.asarray(g["expected_dist"], np.float64))
    vis = visibility * certainty > 0.5
    # The query frame itself is visible by definition.
    P = vis.shape[0]
    vis[np.arange(P), g["query_index"]] = True
    return _finish_tracks(g["xy"], vis, certainty, g["query_index"], p)


def _ground_truth_tracks(gt: Mapping[str, Any], split: Split, timesteps: np.ndarray, p) -> Tracks | None:
    """Synthetic ground truth (P, T_obs) over observed steps -> observed frames."""
    if "tracks2d" not in gt:
        return None
    cols = np.searchsorted(split.observed_timesteps, timesteps)
    xy = np.asarray(gt["tracks2d"], np.float32)[:, cols]
    vis = gt.get("visible")
    vis = np.ones(xy.shape[:2], bool) if vis is None else (np.asarray(vis) > 0)[:, cols]
    return _finish_tracks(xy, vis, None, None, p)


def _composite_tracks(tr: Tracks, order: np.ndarray) -> Tracks:
    """Tracks over frames in temporal order -> columns in the split's order."""
    F = len(order)
    inv = np.empty(F, np.int64)
    inv[order] = np.arange(F)
    # column order[k] of the output is column k of the sorted tracks
    out = Tracks(
        query_index=order[tr.query_index] if tr.num_tracks else tr.query_index,
        xy=tr.xy[:, inv],
        visible=tr.visible[:, inv],
        confidence=tr.confidence[:, inv],
        fb_error=None if tr.fb_error is None else tr.fb_error[:, inv],
        stats=tr.stats,
    )
    return out
