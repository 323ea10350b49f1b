"""Grouping quality against ground-truth instance masks (computed by the
grouping_quality stage, mogaf.grouping.quality: the group stage never opens
held-out views).

Protocol (held-out cameras at observed times, split role
"evaluation_observed"):
- render the group labels of the model at each frame's time step as one-hot
  feature channels with the model's own opacities, scales and deformed
  poses (trajectories at that step); background Gaussians, if any, render a
  separate "background" channel so they occlude as in the RGB render;
- predicted label of a pixel = argmax channel where the rendered alpha
  exceeds `alpha` (0.5), background otherwise (also where the
  background channel wins);
- per-object IoU: for each GT instance, the pixels of all groups whose
  identity (group_instance_id) is that instance against its GT mask,
  intersections and unions summed over all frames (a dataset-level IoU);
- adjusted Rand index between GT instance ids and predicted group ids
  (fragments of one object count as different clusters) over the pixels
  that are foreground in the GT or in the prediction (pixels =
  "foreground", default) or over all pixels ("all"), pooled over frames.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from sklearn.metrics import adjusted_rand_score

from ..errors import MogafError
from ..rendering import render_model
from .core import Groups


def render_group_labels(
    model,
    group_id: np.ndarray,
    num_groups: int,
    timestep: int,
    K: np.ndarray,
    w2c: np.ndarray,
    width: int,
    height: int,
    alpha_threshold: float = 0.5,
    backend: str = "auto",
) -> np.ndarray:
    """(H,W) int64 label image at an observed time step: 0 background, k+1 for group k."""
    n_fg = len(model.fg)
    n_bg = 0 if model.bg is None else len(model.bg)
    if n_fg + n_bg == 0:
        return np.zeros((height, width), dtype=np.int64)
    C = num_groups + 1
    onehot = np.zeros((n_fg + n_bg, C))
    if n_fg:
        onehot[np.arange(n_fg), np.asarray(group_id) + 1] = 1.0
    onehot[n_fg:, 0] = 1.0  # background Gaussians occlude as in the RGB render
    out = render_model(model, int(timestep), K, w2c, width, height, features=onehot, backend=backend)
    img = out.features.detach().cpu().numpy().reshape(height, width, C)
    alpha = out.alpha.detach().cpu().numpy().reshape(height, width)
    label = np.argmax(img, axis=-1).astype(np.int64)
    label[alpha <= alpha_threshold] = 0
    return label


def per_object_iou(gt: np.ndarray, pred_instance: np.ndarray, object_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Intersections and unions (len(object_ids),) of instance label images."""
    inter = np.zeros(len(object_ids), dtype=np.int64)
    union = np.zeros(len(object_ids), dtype=np.int64)
    for i, oid in enumerate(object_ids):
        g = gt == oid
        p = pred_instance == oid
        inter[i] = np.count_nonzero(g & p)
        union[i] = np.count_nonzero(g | p)
    return inter, union


def adjusted_rand_index(gt: np.ndarray, pred: np.ndarray) -> float:
    """ARI of two flat labellings (1.0 when both are empty or identical)."""
    gt = np.asarray(gt).reshape(-1)
    pred = np.asarray(pred).reshape(-1)
    if gt.size == 0:
        return 1.0
    return float(adjusted_rand_score(gt, pred))


def ari_section(gt: np.ndarray, pred: np.ndarray, num_objects: int) -> dict[str, Any]:
    """{"ari": ...} where the ground truth has two or more objects; with one,
    {"ari_left_out": why}: the index then only scores object against the
    background pixels the groups cover (values like -0.05 that mean nothing),
    and the object's IoU is the measure."""
    if num_objects < 2:
        return {"ari_left_out": f"{num_objects} object in the ground-truth masks; the per-object IoU measures it"}
    return {"ari": adjusted_rand_index(gt, pred)}


def grouping_quality(
    model, groups: Groups, frames, *, alpha: float = 0.5, pixels: str = "foreground", backend: str = "auto"
) -> dict[str, Any]:
    """Per-object IoU and ARI of rendered group labels against GT masks.

    frames: a mogaf.scene.Scene (e.g. split role "evaluation_observed") with
    instance_mask; frames whose time step is not one of the model's
    observed steps are skipped. Returns {} when there is nothing to compare.
    """
    if pixels not in ("foreground", "all"):
        raise MogafError(f"grouping quality: pixels must be 'foreground' or 'all', got {pixels!r}")
    if frames is None or frames.instance_mask is None or frames.num_frames == 0:
        return {}
    observed_steps = {int(s) for s in np.asarray(model.timesteps, dtype=np.int64)}
    if frames.instances is not None and len(frames.instances.ids):
        object_ids = np.asarray(frames.instances.ids, dtype=np.int64)
        names = list(frames.instances.names)
    else:
        object_ids = np.unique(frames.instance_mask)
        object_ids = object_ids[object_ids != 0].astype(np.int64)
        names = [f"instance{int(i)}" for i in object_ids]
    inst_of_group = np.r_[0, np.asarray(groups.instance_id, dtype=np.int64)]  # label 0 -> background
    inter = np.zeros(len(object_ids), dtype=np.int64)
    union = np.zeros(len(object_ids), dtype=np.int64)
    gt_all: list[np.ndarray] = []
    pr_all: list[np.ndarray] = []
    used = 0
    for f in range(frames.num_frames):
        step = int(frames.time_index[f])
        if step not in observed_steps:
            continue
        gt = np.asarray(frames.instance_mask[f], dtype=np.int64)
        H, W = gt.shape
        label = render_group_labels(
            model, groups.group_id, groups.num_groups, step, frames.K[f], frames.w2c[f], W, H, float(alpha), backend
        )
        pred_inst = inst_of_group[label]
        pred_inst[label == 0] = 0
        i, u = per_object_iou(gt, pred_inst, object_ids)
        inter += i
        union += u
        sel = (gt != 0) | (label != 0) if pixels == "foreground" else np.ones_like(gt, dtype=bool)
        gt_all.append(gt[sel])
        pr_all.append(label[sel])
        used += 1
    if used == 0:
        return {}
    present = union > 0
    iou = np.where(present, inter / np.maximum(union, 1), 0.0)
    gt_flat = np.concatenate(gt_all)
    pr_flat = np.concatenate(pr_all)
    return {
        **ari_section(gt_flat, pr_flat, int(present.sum())),
        "mean_iou": float(iou[present].mean()) if present.any() else 0.0,
        "object_ids": [int(i) for i in object_ids[present]],
        "object_names": [names[i] for i in np.flatnonzero(present)],
        "per_object_iou": [float(v) for v in iou[present]],
        "num_frames": int(used),
        "num_pixels": int(gt_flat.size),
        "pixels": str(pixels),
        "alpha_threshold": float(alpha),
    }
