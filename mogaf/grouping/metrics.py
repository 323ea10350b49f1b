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
- per-object IoU: for each GT instance, the pixels of all groups assigned to
  it against its GT mask, intersections and unions summed over all frames (a
  dataset-level IoU). A group is assigned the instance it came from
  (group_instance_id) where the grouping read instance masks; otherwise (a
  scene that ships none, scored with its ground-truth segments) the instance
  it overlaps most, or none where that is the background;
- per-part IoU, for objects made of pieces that move differently (ground-
  truth segments with several parts, e.g. a chest's body and lid): each group
  is assigned the segment it overlaps most, then IoU per segment as above;
- adjusted Rand index between GT instance ids and predicted group ids
  (fragments of one object count as different clusters) over the pixels
  that are foreground in the GT or in the prediction (pixels =
  "foreground", default) or over all pixels ("all"), pooled over frames.
"""

from __future__ import annotations

from typing import Any

import numpy as np

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
    # Pair counting (Hubert & Arabie) over the contingency table, in Python
    # integers: the pair products overflow int64 from a few million pixels.
    # Not scikit-learn's function: importing sklearn.metrics costs seconds a process.
    _, gi = np.unique(gt, return_inverse=True)
    _, pi = np.unique(pred, return_inverse=True)
    table = np.bincount(gi.ravel() * (int(pi.max()) + 1) + pi.ravel()).astype(np.int64)
    n = int(gt.size)
    rows = np.bincount(gi.ravel()).astype(np.int64)
    cols = np.bincount(pi.ravel()).astype(np.int64)
    same_both = int((table * table).sum()) - n  # ordered pairs together in both labellings
    same_gt = int((rows * rows).sum()) - n
    same_pred = int((cols * cols).sum()) - n
    if same_gt == same_both and same_pred == same_both:
        return 1.0  # the same partition (also: every point alone, or all in one cluster, in both)
    only_gt, only_pred = same_gt - same_both, same_pred - same_both
    apart_both = n * n - n - same_both - only_gt - only_pred
    num = 2 * (same_both * apart_both - only_gt * only_pred)
    den = (same_both + only_gt) * (only_gt + apart_both) + (same_both + only_pred) * (only_pred + apart_both)
    return float(num / den)


def ari_section(gt: np.ndarray, pred: np.ndarray, num_objects: int) -> dict[str, Any]:
    """{"ari": ...} where the ground truth has two or more objects; with one,
    {"ari_left_out": why}: the index then only scores object against the
    background pixels the groups cover (values like -0.05 that mean nothing),
    and the object's IoU is the measure."""
    if num_objects < 2:
        return {"ari_left_out": f"{num_objects} object in the ground-truth masks; the per-object IoU measures it"}
    return {"ari": adjusted_rand_index(gt, pred)}


def assigned_iou(overlap: np.ndarray, assigned: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Intersections and unions (M,) of M GT labels from an overlap matrix
    (G + 1 predicted labels incl. background row 0, M + 1 GT labels incl.
    background column 0) when predicted label g counts for GT label
    assigned[g] (0: none)."""
    M = overlap.shape[1] - 1
    inter = np.zeros(M, np.int64)
    pred = np.zeros(M, np.int64)
    rows = overlap.sum(axis=1)
    for g in range(1, overlap.shape[0]):
        m = int(assigned[g])
        if m > 0:
            inter[m - 1] += overlap[g, m]
            pred[m - 1] += rows[g]
    union = overlap[:, 1:].sum(axis=0) + pred - inter
    return inter, union


def largest_overlap(overlap: np.ndarray) -> np.ndarray:
    """(G + 1,) the GT label each predicted label overlaps most (0: background; row 0 stays 0)."""
    assigned = np.argmax(overlap, axis=1)
    assigned[0] = 0
    return assigned


def _segment_scores(
    overlap: np.ndarray, segments, group_instance: np.ndarray | None
) -> tuple[np.ndarray, list[str], np.ndarray, np.ndarray, dict[str, Any]]:
    """Per-object and per-part IoU from the overlap of rendered group labels
    with GT segments: the objects' ids and names, their intersections and
    unions, and the section's further keys (matching, parts)."""
    object_ids = np.array(list(dict.fromkeys(segments.instance.tolist())), dtype=np.int64)
    column = {int(i): k + 1 for k, i in enumerate(object_ids)}
    object_names = [segments.names[int(np.flatnonzero(segments.instance == i)[0])].split("/")[0] for i in object_ids]
    # overlap with whole objects: the columns of each object's segments summed
    col_obj = np.array([0] + [column[int(i)] for i in segments.instance], dtype=np.int64)
    by_object = np.zeros((overlap.shape[0], len(object_ids) + 1), np.int64)
    np.add.at(by_object.T, col_obj, overlap.T)
    if group_instance is None:
        assigned = largest_overlap(by_object)
    else:
        assigned = np.array([0] + [column.get(int(i), 0) for i in group_instance], dtype=np.int64)
    inter, union = assigned_iou(by_object, assigned)
    out: dict[str, Any] = {"object_matching": "largest overlap" if group_instance is None else "mask identity"}
    multi = [s for s in range(len(segments.names)) if np.count_nonzero(segments.instance == segments.instance[s]) > 1]
    if multi:
        p_inter, p_union = assigned_iou(overlap, largest_overlap(overlap))
        present = [s for s in multi if p_union[s] > 0]
        out["part_names"] = [segments.names[s] for s in present]
        out["per_part_iou"] = [float(p_inter[s] / p_union[s]) for s in present]
    return object_ids, object_names, inter, union, out


def _masks_name_the_objects(frames, segments) -> bool:
    """Whether the instance masks the grouping read are the ground-truth
    objects (same ids and names), so that a group's mask identity says which
    object it is; a foreground-only mask (a scene shipping no masks) is not."""
    if frames.instances is None or frames.instance_mask is None:
        return False
    listed = dict(zip(np.asarray(frames.instances.ids).tolist(), frames.instances.names, strict=True))
    return all(
        listed.get(int(i)) == name.split("/")[0] for i, name in zip(segments.instance, segments.names, strict=True)
    )


def grouping_quality(
    model,
    groups: Groups,
    frames,
    *,
    alpha: float = 0.5,
    pixels: str = "foreground",
    backend: str = "auto",
) -> dict[str, Any]:
    """Per-object IoU and ARI of rendered group labels against GT masks.

    frames: a mogaf.scene.Scene (e.g. split role "evaluation_observed") with
    ground-truth segments (frames.segments, preferred: they also score parts
    and scenes that ship no masks) or instance_mask; frames whose time step is
    not one of the model's observed steps are skipped. Returns {} when there
    is nothing to compare.
    """
    if pixels not in ("foreground", "all"):
        raise MogafError(f"grouping quality: pixels must be 'foreground' or 'all', got {pixels!r}")
    segments = None if frames is None else frames.segments
    if frames is None or frames.num_frames == 0 or (frames.instance_mask is None and segments is None):
        return {}
    observed_steps = {int(s) for s in np.asarray(model.timesteps, dtype=np.int64)}
    if segments is not None:
        names = list(segments.names)
        object_ids = None
        gt_labels = segments.label
        num_gt = len(names)
    else:
        if frames.instances is not None and len(frames.instances.ids):
            object_ids = np.asarray(frames.instances.ids, dtype=np.int64)
            names = list(frames.instances.names)
        else:
            object_ids = np.unique(frames.instance_mask)
            object_ids = object_ids[object_ids != 0].astype(np.int64)
            names = [f"instance{int(i)}" for i in object_ids]
        # GT label k + 1 for object_ids[k], 0 background
        lookup = {int(i): k + 1 for k, i in enumerate(object_ids)}
        gt_labels = None
        num_gt = len(object_ids)
    G = groups.num_groups
    overlap = np.zeros((G + 1, num_gt + 1), np.int64)
    gt_all: list[np.ndarray] = []
    pr_all: list[np.ndarray] = []
    used = 0
    for f in range(frames.num_frames):
        step = int(frames.time_index[f])
        if step not in observed_steps:
            continue
        if gt_labels is not None:
            gt = gt_column = np.asarray(gt_labels[f], dtype=np.int64)
        else:
            gt = np.asarray(frames.instance_mask[f], dtype=np.int64)  # raw ids: the ARI's labels
            gt_column = np.zeros_like(gt)
            for i, k in lookup.items():
                gt_column[gt == i] = k
        H, W = gt.shape
        label = render_group_labels(
            model, groups.group_id, G, step, frames.K[f], frames.w2c[f], W, H, float(alpha), backend
        )
        overlap += np.bincount(
            label.ravel() * (num_gt + 1) + gt_column.ravel(), minlength=(G + 1) * (num_gt + 1)
        ).reshape(G + 1, num_gt + 1)
        sel = (gt != 0) | (label != 0) if pixels == "foreground" else np.ones_like(gt, dtype=bool)
        gt_all.append(gt[sel])
        pr_all.append(label[sel])
        used += 1
    if used == 0:
        return {}
    extra: dict[str, Any] = {}
    if segments is not None:
        object_ids, names, inter, union, extra = _segment_scores(
            overlap, segments, groups.instance_id if _masks_name_the_objects(frames, segments) else None
        )
        gt_flat = np.r_[0, segments.instance][np.concatenate(gt_all)]  # the ARI is over objects, not parts
    else:
        column = np.array([0] + [lookup.get(int(i), 0) for i in groups.instance_id], dtype=np.int64)
        inter, union = assigned_iou(overlap, column)
        gt_flat = np.concatenate(gt_all)
    present = union > 0
    iou = np.where(present, inter / np.maximum(union, 1), 0.0)
    pr_flat = np.concatenate(pr_all)
    return {
        **ari_section(gt_flat, pr_flat, int(present.sum())),
        "mean_iou": float(iou[present].mean()) if present.any() else 0.0,
        "object_ids": [int(i) for i in np.asarray(object_ids)[present]],
        "object_names": [names[i] for i in np.flatnonzero(present)],
        "per_object_iou": [float(v) for v in iou[present]],
        **extra,
        "num_frames": int(used),
        "num_pixels": int(gt_flat.size),
        "pixels": str(pixels),
        "alpha_threshold": float(alpha),
    }
