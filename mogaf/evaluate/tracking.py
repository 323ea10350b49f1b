"""Tracking metrics of a forecast: ground-truth surface points carried by the forecast poses.

GT points are attached to their nearest Gaussians at the last observed step
(in each Gaussian's local frame) and carried by the forecast poses; 3D EPE,
delta_3D, and on the train camera 2D AJ, delta_avg and occlusion accuracy
(visibility from the rendered depth). Synthetic scenes only (they have GT
tracks).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from .. import metrics as M
from ..camera import project
from ..rendering import render_poses
from ..representation import Model4D, quat_to_matrix
from ..split import Split, load_frames, load_ground_truth
from .params import EvaluateSettings, load_settings


def attach_points(
    points: np.ndarray, means: np.ndarray, quats: np.ndarray, k: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Attach points (P,3) to their k nearest Gaussians at one time.

    Returns neighbour ids (P,k), inverse-distance weights (P,k) summing to 1,
    and each point's offset in each neighbour's local frame (P,k,3).
    """
    import torch
    from scipy.spatial import cKDTree

    k = max(1, min(int(k), means.shape[0]))
    dist, idx = cKDTree(means).query(points, k=k)
    dist = dist.reshape(len(points), k)
    idx = idx.reshape(len(points), k)
    w = 1.0 / np.maximum(dist, 1e-9)
    w /= w.sum(axis=1, keepdims=True)
    R = quat_to_matrix(torch.as_tensor(quats, dtype=torch.float64)).numpy()  # (N,3,3)
    rel = points[:, None, :] - means[idx]
    offsets = np.einsum("pkji,pkj->pki", R[idx], rel)  # R^T (p - mu)
    return idx, w, offsets


def carry_points(
    idx: np.ndarray, weights: np.ndarray, offsets: np.ndarray, means: np.ndarray, quats: np.ndarray
) -> np.ndarray:
    """Positions (P,T,3) of attached points under per-Gaussian poses (N,T,3/4)."""
    import torch

    R = quat_to_matrix(torch.as_tensor(quats[idx], dtype=torch.float64)).numpy()  # (P,k,T,3,3)
    pos = np.einsum("pktij,pkj->pkti", R, offsets) + means[idx]  # (P,k,T,3)
    return np.einsum("pk,pkti->pti", weights, pos)


# m: a ground-truth point whose positions stay this close to its last observed
# one never moves (a synthetic scene's ground truth is exact)
STILL_TOLERANCE = 1e-6


def still_points(observed: np.ndarray, *later: np.ndarray) -> np.ndarray:
    """(P,) ground-truth points that never move: every position of `observed`
    (P, T, 3) and of the `later` arrays (P, T', 3) within STILL_TOLERANCE of
    the last observed one (a point without a finite position is not still)."""
    ref = np.asarray(observed, np.float64)[:, -1:]
    still = np.ones(ref.shape[0], bool)
    for positions in (observed, *later):
        gap = np.linalg.norm(np.asarray(positions, np.float64) - ref, axis=-1)
        still &= np.all(np.isfinite(gap) & (gap <= STILL_TOLERANCE), axis=1)
    return still


def still_points_displacement(pred3d: np.ndarray, observed: np.ndarray, future: np.ndarray) -> dict[str, Any]:
    """How far a forecast moves what does not move: of the ground-truth points
    still over the observed (P, T, 3) and forecast (P, T_fc, 3) steps, their
    number and their carried positions' (pred3d) mean distance from where
    they rest over the forecast steps (without such points, the number alone)."""
    still = still_points(observed, future)
    out: dict[str, Any] = {"still_points": int(still.sum())}
    if still.any():
        rest = np.asarray(observed, np.float64)[still, -1:]
        out["still_points_displacement"] = float(np.linalg.norm(pred3d[still] - rest, axis=-1).mean())
    return out


def predicted_gt_tracks(model: Model4D, fc: dict[str, Any], gt_observed: Mapping[str, Any], k: int) -> np.ndarray:
    """Forecast positions (P, T_fc, 3) of the ground-truth surface points."""
    last = model.trajectory_means.shape[1] - 1
    points_last = np.asarray(gt_observed["points3d"], np.float64)[:, -1]
    idx, w, off = attach_points(
        points_last,
        np.asarray(model.trajectory_means[:, last], np.float64),
        np.asarray(model.trajectory_quats[:, last], np.float64),
        k,
    )
    return carry_points(idx, w, off, np.asarray(fc["means"], np.float64), np.asarray(fc["quats"], np.float64))


def tracking_section(
    model: Model4D, fc: dict[str, Any], scene_h5: str, split: Split, params: Mapping[str, Any] | EvaluateSettings
) -> tuple[dict[str, Any] | None, dict[str, Any] | None]:
    """Tracking metrics of the GT surface points carried by the forecast, and
    the quick 3D checks: `epe_3d_quick`, their mean distance from the GT over
    every point and forecast step (no visibility, no unit scaling), and
    still_points_displacement's. (None, None) without GT."""
    settings = load_settings(params)
    gt_obs = load_ground_truth(scene_h5, split, "observed")
    if "points3d" not in gt_obs:
        return None, None
    gt_fc = load_ground_truth(scene_h5, split, "forecast")
    pred3d = predicted_gt_tracks(model, fc, gt_obs, int(settings.tracking_neighbors))
    gt3d = np.asarray(gt_fc["points3d"], np.float64)
    quick = {
        "epe_3d_quick": float(np.mean(np.linalg.norm(pred3d - gt3d, axis=-1))),
        **still_points_displacement(pred3d, gt_obs["points3d"], gt3d),
    }
    P, T = gt3d.shape[:2]
    gt_vis = np.asarray(gt_fc.get("visible", np.ones((P, T), bool)), bool)
    pred2d = gt2d = pred_vis = None
    steps_2d = None  # the forecast steps the 2D metrics score: those the training camera has a frame of
    if "tracks2d" in gt_fc and split.frame_ids["train_future"].size:
        frames = load_frames(scene_h5, split, "train_future")
        by_t = {int(t): f for f, t in enumerate(frames.time_index)}
        steps_2d = np.array([int(t) in by_t for t in split.forecast_timesteps])
        pred2d = np.zeros((P, T, 2))
        pred_vis = np.zeros((P, T), bool)
        for i, t in enumerate(split.forecast_timesteps):
            f = by_t.get(int(t))
            if f is None:
                continue
            uv, z = project(pred3d[:, i], frames.K[f], frames.w2c[f])
            pred2d[:, i] = uv
            out = render_poses(
                model, fc["means"][:, i], fc["quats"][:, i], frames.K[f], frames.w2c[f], frames.width, frames.height
            )
            depth = out.depth[..., 0].detach().cpu().numpy()
            col = np.clip(np.floor(uv[:, 0]).astype(int), 0, frames.width - 1)
            row = np.clip(np.floor(uv[:, 1]).astype(int), 0, frames.height - 1)
            inside = (
                (uv[:, 0] >= 0) & (uv[:, 0] < frames.width) & (uv[:, 1] >= 0) & (uv[:, 1] < frames.height) & (z > 0)
            )
            surface = depth[row, col]
            pred_vis[:, i] = inside & (z <= surface * (1.0 + float(settings.visibility_tolerance)))
        gt2d = np.asarray(gt_fc["tracks2d"], np.float64)
    common = {
        "gt_vis": gt_vis,
        "aj_thresholds": tuple(settings.aj_thresholds),
        "pck_thresholds": tuple(settings.delta_thresholds),
        "strict": False,
    }
    res = M.tracking_metrics(pred_3d=pred3d, gt_3d=gt3d, scale=float(settings.tracking_scale), **common)
    if steps_2d is not None and steps_2d.any():
        # a step the training camera has no frame of has no predicted 2D track: the 2D metrics leave it out
        mask = np.broadcast_to(steps_2d[None, :], (P, T))
        res.update(M.tracking_metrics(pred_vis=pred_vis, pred_2d=pred2d, gt_2d=gt2d, eval_mask=mask, **common))
    return {k: (None if v is None else float(v)) for k, v in res.items()}, quick
