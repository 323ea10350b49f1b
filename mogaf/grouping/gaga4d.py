"""Gaga-4D: the naive 4D extension of Gaga's memory bank (supp. Algorithm 2).

For every observed frame in time order (stride `gaga_frame_stride`) and
every mask identity k present in it:
  G_k^t  = front Gaussians whose deformed centre at t projects into M_k^t
           (Gaga's patch-wise front selection, Gaga's default front
           percentage 0.2);
  Overlap = #(G_k ∩ G_k^t) / #(G_k^t)   (the supplementary's definition;
           intersection by canonical identity, i.e. Gaussian index);
  if Overlap >= theta_ov (Gaga's default overlap threshold 0.1) the
  Gaussians of G_k^t join G_k; otherwise a new group is opened in the
  memory bank with G_k^t, carrying identity k (as Gaga opens a new group
  for an unmatched mask). This is how the baseline fragments one object
  into several groups, the failure the paper describes. When identity k
  already has several groups, the one with the largest overlap is tested.

Memory bank rule (Gaga): a Gaussian is in at most one group, the first it
was put in; Gaussians already owned by another group count in #(G_k^t) but
are not moved.

To give every Gaussian a label (the quality metric and the later stages
need a complete labelling), Gaussians that no mask ever claimed are labelled
by the same KNN voting as ours (8 neighbours, closest half per round), but
in canonical-mean space only: the baseline uses no motion cue.
"""

from __future__ import annotations

import numpy as np

from .core import MaskFrames, frames_in_time_order, mask_gaussians
from .params import load_settings
from .voting import knn_vote

SEED, VOTE = 0, 2


def group_gaga4d(
    model,
    masks: np.ndarray,
    frames: MaskFrames,
    instance_ids: np.ndarray,
    params: dict,
    frame_order: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Returns labels (N,) indexing groups, group_instance (G,) indexing
    instance_ids, assignment stage per Gaussian and diagnostics."""
    params = load_settings(params)
    N = len(model.fg)
    labels = np.full(N, -1, dtype=np.int64)
    stage = np.full(N, -1, dtype=np.int8)
    group_instance: list[int] = []
    group_size: list[int] = []
    theta = float(params.overlap_threshold)
    if frame_order is None:
        frame_order = frames_in_time_order(frames.time_index)[:: int(params.gaga_frame_stride)]
    traj = model.trajectory_means
    merges = new_groups = 0
    for f in np.asarray(frame_order, dtype=np.int64):
        idx, inst = mask_gaussians(
            np.asarray(traj[:, frames.time_index[f]], dtype=np.float64),
            masks[f],
            frames.K[f],
            frames.w2c[f],
            instance_ids,
            float(params.gaga_front_fraction),
            int(params.front_patches),
        )
        if idx.size == 0:
            continue
        bounds = np.flatnonzero(np.r_[True, inst[1:] != inst[:-1], True])
        for a, b in zip(bounds[:-1], bounds[1:]):
            j = int(inst[a])
            G = idx[a:b]
            candidates = [g for g, gi in enumerate(group_instance) if gi == j]
            target = -1
            if candidates:
                owned = labels[G]
                overlaps = np.array([np.count_nonzero(owned == g) for g in candidates], dtype=np.float64) / G.size
                best = int(np.argmax(overlaps))
                if overlaps[best] >= theta:
                    target = candidates[best]
                    merges += 1
            if target < 0:
                target = len(group_instance)
                group_instance.append(j)
                group_size.append(0)
                new_groups += 1
            free = G[labels[G] < 0]
            labels[free] = target
            stage[free] = SEED
            group_size[target] += free.size
    means = np.asarray(model.fg.means, dtype=np.float64)
    before = labels < 0
    labels, rounds = knn_vote(means, labels, int(params.vote_knn), float(params.vote_fraction))
    stage[before & (labels >= 0)] = VOTE
    diag = {"frames": int(len(frame_order)), "merges": merges, "groups_opened": new_groups, "vote_rounds": rounds}
    return labels, np.asarray(group_instance, dtype=np.int64), stage, diag
