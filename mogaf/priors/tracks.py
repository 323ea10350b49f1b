"""Long-range 2D point tracks by chaining dense optical flow.

`compute_flow_tracks` works on any video (frames (T, H, W, 3) uint8):

1. dense flow between consecutive frames, both directions (DIS or RLOF);
2. query points on a regular grid (stride `grid_stride`) inside the
   foreground of `num_query_frames` evenly spaced query frames; points of a
   later query frame closer than `dedup_radius_px` to a track already visible
   there are skipped, so new points go where coverage is missing;
3. each point is chained forward (q -> T-1) and backward (q -> 0) through the
   flows; a step is accepted when the forward-backward error
   |x + f(x) + b(x + f(x)) - x| is at most
   `fb_threshold_px + fb_relative * |f(x)|`, the point stays
   `border_px` inside the image and the mean absolute RGB difference (in
   [0, 1]) between its (2 r + 1)^2 patch before and after the step, r =
   `photometric_patch_radius`, is at most `photometric_threshold` (this
   catches points dragged along by an occluding edge, whose flow is
   forward-backward consistent). The first
   failed step ends the chain in that direction: the point is invisible from
   there on (occluded, left the image or lost) and keeps its last position;
4. tracks visible in fewer than `min_track_length` frames are dropped.

Positions are returned in the image convention of mogaf.camera (pixel
centres at i + 0.5). Confidence decays with the forward-backward error
accumulated along the chain: exp(-sum(err) / (2 * fb_threshold_px)), 0 where
invisible. `fb_error[p, t]` is the error of the step that reached frame t
(0 at the query frame and where invisible).

Limitation: chained flow cannot re-find a point after an occlusion; a point
that reappears is not re-identified (a later query frame starts a new track).
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy.spatial import cKDTree

from .flow import consecutive_flows, sample, sample_patches
from .params import load_settings  # the single documented source of defaults


@dataclass
class Tracks:
    query_index: np.ndarray  # (P,) int64, frame where the point was queried
    xy: np.ndarray  # (P, T, 2) float32, pixel centres at i + 0.5
    visible: np.ndarray  # (P, T) bool
    confidence: np.ndarray  # (P, T) float32 in [0, 1]
    fb_error: np.ndarray | None = None  # (P, T) float32, px
    stats: dict[str, Any] = field(default_factory=dict)

    @property
    def num_tracks(self) -> int:
        return int(self.xy.shape[0])

    def subset(self, keep: np.ndarray) -> Tracks:
        return Tracks(
            query_index=self.query_index[keep],
            xy=self.xy[keep],
            visible=self.visible[keep],
            confidence=self.confidence[keep],
            fb_error=None if self.fb_error is None else self.fb_error[keep],
            stats=dict(self.stats),
        )


def empty_tracks(T: int) -> Tracks:
    return Tracks(
        query_index=np.zeros(0, np.int64),
        xy=np.zeros((0, T, 2), np.float32),
        visible=np.zeros((0, T), bool),
        confidence=np.zeros((0, T), np.float32),
        fb_error=np.zeros((0, T), np.float32),
    )


def query_frames(T: int, n: int) -> np.ndarray:
    """`n` evenly spaced frame indices in [0, T-1] (all frames if n >= T)."""
    if T <= 0:
        return np.zeros(0, np.int64)
    n = max(1, min(int(n), T))
    return np.unique(np.round(np.linspace(0, T - 1, n)).astype(np.int64))


def grid_points(H: int, W: int, stride: int, mask: np.ndarray | None, border: float) -> np.ndarray:
    """Grid pixel centres (array coordinates) inside `mask`, away from the border."""
    stride = max(1, int(stride))
    off = stride // 2
    xs = np.arange(off, W, stride)
    ys = np.arange(off, H, stride)
    gx, gy = np.meshgrid(xs, ys)
    keep = (gx >= border) & (gx <= W - 1 - border) & (gy >= border) & (gy <= H - 1 - border)
    if mask is not None:
        keep &= mask[gy, gx]
    return np.stack([gx[keep], gy[keep]], axis=-1).astype(np.float32)


def _chain(
    pos0: np.ndarray,
    q: int,
    step: int,
    flows_to: np.ndarray,
    flows_back: np.ndarray,
    blurred: np.ndarray,
    out_xy: np.ndarray,
    out_vis: np.ndarray,
    out_err: np.ndarray,
    p: Mapping[str, Any],
) -> None:
    """Chain points from frame q in direction `step` (+1 or -1), writing in place."""
    T, H, W = blurred.shape[:3]
    border = float(p.border_px)
    fb_thr = float(p.fb_threshold_px)
    fb_rel = float(p.fb_relative)
    photo = float(p.photometric_threshold)
    pos = pos0.copy()
    alive = np.ones(len(pos), bool)
    r = int(p.photometric_patch_radius)
    offs = np.stack(np.meshgrid(np.arange(-r, r + 1), np.arange(-r, r + 1)), -1).reshape(-1, 2).astype(np.float32)
    t = q
    while 0 <= t + step < T and alive.any():
        idx = np.flatnonzero(alive)
        # Flow index: forward t->t+1 is flows[t]; backward t->t-1 is flows[t-1].
        k = t if step > 0 else t - 1
        cur = pos[idx]
        f = sample(flows_to[k], cur)
        new = cur + f
        b = sample(flows_back[k], new)
        err = np.linalg.norm(new + b - cur, axis=1)
        ok = err <= fb_thr + fb_rel * np.linalg.norm(f, axis=1)
        ok &= (new[:, 0] >= border) & (new[:, 0] <= W - 1 - border)
        ok &= (new[:, 1] >= border) & (new[:, 1] <= H - 1 - border)
        if photo > 0:
            # Patch appearance must persist from one frame to the next.
            before = sample_patches(blurred[t], cur, offs)
            after = sample_patches(blurred[t + step], new, offs)
            ok &= np.abs(after - before).mean(axis=(1, 2)) <= photo
        good = idx[ok]
        pos[good] = new[ok]
        alive[idx[~ok]] = False
        t += step
        out_xy[:, t] = pos  # lost points keep their last position
        out_vis[good, t] = True
        out_err[good, t] = err[ok]
    # Frames the loop never reached keep the last position too.
    if step > 0 and t + 1 < T:
        out_xy[:, t + 1 :] = pos[:, None]
    elif step < 0 and t > 0:
        out_xy[:, :t] = pos[:, None]


def compute_flow_tracks(
    frames: np.ndarray,
    fg_masks: np.ndarray | None,
    params: Mapping[str, Any] | None = None,
    *,
    flows: tuple[np.ndarray, np.ndarray] | None = None,
) -> Tracks:
    """Track grid points through a video by chained optical flow (see module doc).

    frames: (T, H, W, 3) uint8 in temporal order; fg_masks: (T, H, W) bool
    (query points only inside them) or None (whole frame). `flows` lets a
    caller reuse (forward, backward) flows from `consecutive_flows`.
    """
    p = load_settings(params)
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8:
        raise ValueError(f"frames must be (T, H, W, 3) uint8, got {frames.shape} {frames.dtype}")
    T, H, W = frames.shape[:3]
    if fg_masks is not None:
        fg_masks = np.asarray(fg_masks, bool)
        if fg_masks.shape != (T, H, W):
            raise ValueError(f"fg_masks must be {(T, H, W)}, got {fg_masks.shape}")
    t0 = time.perf_counter()
    fwd, bwd = flows if flows is not None else consecutive_flows(frames, p)
    t_flow = time.perf_counter() - t0
    sigma = 1.0
    blurred = np.stack([cv2.GaussianBlur(f.astype(np.float32) / 255.0, (0, 0), sigma) for f in frames])

    parts: list[Tracks] = []
    border = float(p.border_px)
    dedup = float(p.dedup_radius_px)
    for q in query_frames(T, int(p.num_query_frames)):
        pts = grid_points(H, W, int(p.grid_stride), None if fg_masks is None else fg_masks[q], border)
        if dedup > 0 and parts and len(pts):
            have = np.concatenate([tr.xy[tr.visible[:, q], q] for tr in parts]) - 0.5
            if len(have):
                dist, _ = cKDTree(have).query(pts, k=1)
                pts = pts[dist > dedup]
        n = len(pts)
        if n == 0:
            continue
        xy = np.zeros((n, T, 2), np.float32)
        vis = np.zeros((n, T), bool)
        err = np.zeros((n, T), np.float32)
        xy[:, q] = pts
        vis[:, q] = True
        _chain(pts, int(q), +1, fwd, bwd, blurred, xy, vis, err, p)
        _chain(pts, int(q), -1, bwd, fwd, blurred, xy, vis, err, p)
        xy += 0.5
        parts.append(Tracks(np.full(n, q, np.int64), xy, vis, np.zeros((n, T), np.float32), err))

    if not parts:
        tracks = empty_tracks(T)
    else:
        tracks = Tracks(
            query_index=np.concatenate([t.query_index for t in parts]),
            xy=np.concatenate([t.xy for t in parts]),
            visible=np.concatenate([t.visible for t in parts]),
            confidence=np.concatenate([t.confidence for t in parts]),
            fb_error=np.concatenate([t.fb_error for t in parts]),
        )
    tracks.confidence = _confidence(tracks, float(p.fb_threshold_px))
    keep = tracks.visible.sum(axis=1) >= int(p.min_track_length)
    tracks = tracks.subset(keep)
    cap = int(p.max_tracks)
    if cap > 0 and tracks.num_tracks > cap:
        rng = np.random.default_rng(int(p.seed))
        tracks = tracks.subset(np.sort(rng.choice(tracks.num_tracks, cap, replace=False)))
    tracks.stats = track_statistics(tracks)
    tracks.stats.update(
        flow_seconds=round(t_flow, 3),
        seconds=round(time.perf_counter() - t0, 3),
        num_query_frames=int(len(query_frames(T, int(p.num_query_frames)))),
    )
    return tracks


def _confidence(tracks: Tracks, fb_thr: float) -> np.ndarray:
    """exp(-accumulated fb error from the query frame / (2 fb_thr)); 0 if invisible."""
    P, T = tracks.visible.shape
    conf = np.zeros((P, T), np.float32)
    if P == 0:
        return conf
    err = tracks.fb_error if tracks.fb_error is not None else np.zeros((P, T), np.float32)
    t = np.arange(T)[None, :]
    q = tracks.query_index[:, None]
    fwd = np.cumsum(np.where(t >= q, err, 0.0), axis=1)
    bwd = np.cumsum(np.where(t <= q, err, 0.0)[:, ::-1], axis=1)[:, ::-1]
    acc = np.where(t >= q, fwd, bwd)
    conf[:] = np.exp(-acc / (2.0 * max(fb_thr, 1e-6)))
    conf[~tracks.visible] = 0.0
    return conf


def track_statistics(tracks: Tracks) -> dict[str, Any]:
    """Count, mean visible length and forward-backward error percentiles (px)."""
    P, T = tracks.visible.shape
    stats: dict[str, Any] = {"count": int(P), "num_frames": int(T)}
    if P == 0:
        stats.update(
            mean_length=0.0, visible_fraction=0.0, fb_error_median_px=0.0, fb_error_p95_px=0.0, fb_error_steps=0
        )
        return stats
    lengths = tracks.visible.sum(axis=1)
    stats["mean_length"] = round(float(lengths.mean()), 3)
    stats["visible_fraction"] = round(float(tracks.visible.mean()), 4)
    if tracks.fb_error is not None:
        step = tracks.visible.copy()
        step[np.arange(P), tracks.query_index] = False  # the query frame has no step
        errs = tracks.fb_error[step]
    else:
        errs = np.zeros(0)
    stats["fb_error_steps"] = int(errs.size)
    stats["fb_error_median_px"] = round(float(np.median(errs)), 4) if errs.size else 0.0
    stats["fb_error_p95_px"] = round(float(np.percentile(errs, 95)), 4) if errs.size else 0.0
    return stats
