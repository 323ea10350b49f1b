"""Grouping quality against ground-truth instance masks.

Protocol (held-out cameras at observed times, split role
"evaluation_observed"):
- render the group labels of the model at each frame's time step as one-hot
  feature channels with the model's own opacities, scales and deformed
  poses (trajectories at that step); background Gaussians, if any, render a
  separate "background" channel so they occlude as in the RGB render;
- predicted label of a pixel = argmax channel where the rendered alpha
  exceeds `quality_alpha` (0.5), background otherwise (also where the
  background channel wins);
- per-object IoU: for each GT instance, the pixels of all groups whose
  identity (group_instance_id) is that instance against its GT mask,
  intersections and unions summed over all frames (a dataset-level IoU);
- adjusted Rand index between GT instance ids and predicted group ids
  (fragments of one object count as different clusters) over the pixels
  that are foreground in the GT or in the prediction (quality_pixels =
  "foreground", default) or over all pixels ("all"), pooled over frames.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import torch
from sklearn.metrics import adjusted_rand_score

from .core import Groups, resolve_params


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.asarray(x, dtype=np.float64)))


def render_group_labels(model, group_id: np.ndarray, num_groups: int, column: int, K: np.ndarray, w2c: np.ndarray,
                        width: int, height: int, alpha_threshold: float = 0.5, backend: str = "auto",
                        rasterize: Callable | None = None) -> np.ndarray:
    """(H,W) int64 label image: 0 background, k+1 for group k."""
    if rasterize is None:
        from ..render import rasterize as _r

        rasterize = _r
    fg = model.fg
    means = [np.asarray(model.trajectory_means[:, column], dtype=np.float64)]
    quats = [np.asarray(model.trajectory_quats[:, column], dtype=np.float64)]
    scales = [np.exp(np.asarray(fg.log_scales, dtype=np.float64))]
    opac = [_sigmoid(fg.opacity_logits).reshape(-1)]
    C = num_groups + 1
    onehot = np.zeros((len(fg), C))
    if len(fg):
        onehot[np.arange(len(fg)), np.asarray(group_id) + 1] = 1.0
    feats = [onehot]
    if model.bg is not None and len(model.bg):
        bg = model.bg
        means.append(np.asarray(bg.means, dtype=np.float64))
        quats.append(np.asarray(bg.quats, dtype=np.float64))
        scales.append(np.exp(np.asarray(bg.log_scales, dtype=np.float64)))
        opac.append(_sigmoid(bg.opacity_logits).reshape(-1))
        b = np.zeros((len(bg), C))
        b[:, 0] = 1.0
        feats.append(b)
    t = lambda arrs: torch.from_numpy(np.concatenate(arrs, 0)).to(torch.float32)  # noqa: E731
    if sum(len(m) for m in means) == 0:
        return np.zeros((height, width), dtype=np.int64)
    with torch.no_grad():
        out = rasterize(t(means), t(quats), t(scales), t(opac), t(feats),
                        torch.from_numpy(np.asarray(w2c, dtype=np.float64)).float(),
                        torch.from_numpy(np.asarray(K, dtype=np.float64)).float(), int(width), int(height),
                        backend=backend)
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


def grouping_quality(model, groups: Groups, frames, params: dict[str, Any] | None = None, *,
                     backend: str = "auto", rasterize: Callable | None = None) -> dict[str, Any]:
    """Per-object IoU and ARI of rendered group labels against GT masks.

    frames: a mogaf.scene.Scene (e.g. split role "evaluation_observed") with
    instance_mask; frames whose time step is not one of the model's
    observed steps are skipped. Returns {} when there is nothing to compare.
    """
    p = resolve_params(params)
    if frames is None or frames.instance_mask is None or frames.num_frames == 0:
        return {}
    steps = np.asarray(model.timesteps, dtype=np.int64)
    column_of = {int(s): i for i, s in enumerate(steps)}
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
        col = column_of.get(int(frames.time_index[f]))
        if col is None:
            continue
        gt = np.asarray(frames.instance_mask[f], dtype=np.int64)
        H, W = gt.shape
        label = render_group_labels(model, groups.group_id, groups.num_groups, col, frames.K[f], frames.w2c[f], W, H,
                                    float(p["quality_alpha"]), backend, rasterize)
        pred_inst = inst_of_group[label]
        pred_inst[label == 0] = 0
        i, u = per_object_iou(gt, pred_inst, object_ids)
        inter += i
        union += u
        sel = (gt != 0) | (label != 0) if p["quality_pixels"] == "foreground" else np.ones_like(gt, dtype=bool)
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
        "ari": adjusted_rand_index(gt_flat, pr_flat),
        "mean_iou": float(iou[present].mean()) if present.any() else 0.0,
        "object_ids": [int(i) for i in object_ids[present]],
        "object_names": [names[i] for i in np.flatnonzero(present)],
        "per_object_iou": [float(v) for v in iou[present]],
        "num_frames": int(used),
        "num_pixels": int(gt_flat.size),
        "pixels": str(p["quality_pixels"]),
        "alpha_threshold": float(p["quality_alpha"]),
    }
