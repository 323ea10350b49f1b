"""Image metrics of a 4D model rendered at held-out views at observed times."""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..errors import input_error
from ..metrics import image_metrics
from ..rendering import render_model
from ..representation import Model4D, load_model
from ..split import Split, evenly_spaced_frame_ids, load_evenly_spaced_frames, load_ground_truth
from .params import load_settings


def observed_motion(
    model: Model4D, gt_points: np.ndarray, neighbors: int, model_h5: str | os.PathLike = "model"
) -> dict[str, float]:
    """How well the model's observed trajectories follow ground-truth surface
    points (P, T, 3) at the model's T observed steps. Each point is attached to
    its nearest Gaussians at the last observed step (as the forecasts' tracking
    metrics attach it) and carried back by their trajectories: the mean 3D
    error over the observed steps, and the mean error of the points' velocity
    (one step's displacement) over every step and over the last one, the
    velocity the forecasts start from, beside the points' mean true speed;
    where some points never move, their number and `still_jitter`, the mean
    distance of their carried positions from their mean position."""
    from ..evaluate.tracking import predicted_gt_tracks, still_points  # local: torch

    gt = np.asarray(gt_points, np.float64)
    means = np.asarray(model.trajectory_means, np.float64)
    quats = np.asarray(model.trajectory_quats, np.float64)
    if gt.ndim != 3 or gt.shape[1:] != (means.shape[1], 3):
        raise input_error(
            model_h5,
            f"the model has {means.shape[1]} observed steps, the scene's ground-truth points have shape {gt.shape} "
            "at the split's observed steps (a model of another split?)",
        )
    gt = gt[np.isfinite(gt).all(axis=(1, 2))]  # a point without a position at some step is left out
    if gt.shape[1] < 2 or gt.shape[0] == 0 or means.shape[0] == 0:
        return {}
    # the forecasts' tracking metrics' attachment, carried by the observed poses instead of a forecast's
    carried = predicted_gt_tracks(model, {"means": means, "quats": quats}, {"points3d": gt}, neighbors)  # (P, T, 3)
    velocity_error = np.linalg.norm(np.diff(carried, axis=1) - np.diff(gt, axis=1), axis=-1)  # (P, T - 1)
    out = {
        "epe_3d": float(np.linalg.norm(carried - gt, axis=-1).mean()),
        "velocity_error": float(velocity_error.mean()),
        "last_velocity_error": float(velocity_error[:, -1].mean()),
        "speed": float(np.linalg.norm(np.diff(gt, axis=1), axis=-1).mean()),
    }
    still = still_points(gt)
    if still.any():
        # the model's own jitter where nothing moves: the forecasts' still_points_displacement is judged against it
        rest = carried[still]
        out["still_points"] = float(still.sum())
        out["still_jitter"] = float(np.linalg.norm(rest - rest.mean(axis=1, keepdims=True), axis=-1).mean())
    return out


def measure_reconstruction_quality(
    model_h5: str | os.PathLike, scene_h5: str | os.PathLike, split: Split, params: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """Image metrics of the model rendered at held-out views at observed
    times: {"frame_ids", "timesteps", "camera_ids", "per_frame"} (no frame when the split
    has none), and "observed_motion" where the scene has ground-truth points
    (observed_motion; {} otherwise)."""
    p = load_settings(params)
    has_views = split.frame_ids.get("evaluation_observed", np.zeros(0)).size > 0
    gt = load_ground_truth(scene_h5, split, "observed", entries=("points3d",))
    model = load_model(model_h5) if has_views or "points3d" in gt else None
    motion = observed_motion(model, gt["points3d"], int(p.tracking_neighbors), model_h5) if "points3d" in gt else {}
    if not has_views:
        return {
            "frame_ids": np.zeros(0, np.int64),
            "timesteps": np.zeros(0, np.int64),
            "camera_ids": np.zeros(0, np.int64),
            "per_frame": [],
            "observed_motion": motion,
        }
    frame_ids = evenly_spaced_frame_ids(split, "evaluation_observed", int(p.max_frames))
    frames = load_evenly_spaced_frames(scene_h5, split, "evaluation_observed", int(p.max_frames))
    masked = split.protocol == "iphone"
    masks = frames.covisibility_masks()
    per_frame = []
    for f in range(frames.num_frames):
        out = render_model(model, int(frames.time_index[f]), frames.K[f], frames.w2c[f], frames.width, frames.height)
        pred = np.clip(out.features[..., :3].detach().cpu().numpy().astype(np.float64), 0, 1)
        per_frame.append(
            image_metrics(pred, frames.images[f] / 255.0, None if masks is None else masks[f], masked, use_lpips=False)
        )
    return {
        "frame_ids": frame_ids,
        "timesteps": np.asarray(frames.time_index, np.int64),
        "camera_ids": np.asarray(frames.camera_id, np.int64),
        "per_frame": per_frame,
        "observed_motion": motion,
    }
