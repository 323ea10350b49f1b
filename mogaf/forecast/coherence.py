"""Does a forecast keep the scene's structure? Two figures per forecast, from
the forecast poses and the observed trajectories only (no ground truth):

  rigid_distance_change: for every dynamic group the grouping calls rigid, the
      mean over forecast steps and member pairs of |d_ij(t) - d_ij(T)|, the
      change of the members' pairwise distances from the last observed frame
      (0 for a forecast that moves the group as one body); the mean over
      groups, also divided by each group's RMS radius (`_rel`). The members
      are the group's moving ones: its still members (below) belong to no
      moving body, whatever the grouping joined them to.
  still_displacement: the mean distance of still Gaussians from their last
      observed position over the forecast. Still: members of dynamic groups
      that never moved more than STILL_FACTOR x their group's noise level
      while observed (mogaf.forecast.trajectory.still_gaussians; in a rigid
      group rigid_group_still, the forecaster's own test: none unless 3
      members move). Members of
      static groups are left out: no forecaster moves them (the merge keeps
      their last pose), so they would only dilute the figure.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mogaf.forecast.trajectory import rigid_group_still, still_gaussians

STILL_FACTOR = 3.0  # fixed here (not the forecaster's setting), so every method is measured alike
MAX_PAIR_MEMBERS = 256  # members sampled per group for the pairwise distances


def rigid_distance_change(last: np.ndarray, future: np.ndarray, rng: np.random.Generator) -> tuple[float, float]:
    """(mean |d_ij(t) - d_ij(T)|, the same over the group's RMS radius) for
    one group: last (G, 3), future (G, n, 3)."""
    g = last.shape[0]
    if g < 2:
        return 0.0, 0.0
    pick = np.sort(rng.choice(g, MAX_PAIR_MEMBERS, replace=False)) if g > MAX_PAIR_MEMBERS else np.arange(g)
    i, j = np.triu_indices(pick.size, k=1)
    a, b = pick[i], pick[j]
    d0 = np.linalg.norm(last[a] - last[b], axis=-1)
    dt = np.linalg.norm(future[a] - future[b], axis=-1)  # (P, n)
    change = float(np.abs(dt - d0[:, None]).mean())
    radius = float(np.sqrt(np.mean(np.sum((last - last.mean(0)) ** 2, axis=-1))))
    return change, (change / radius if radius > 0 else 0.0)


def coherence(
    observed_means: np.ndarray,
    forecast_means: np.ndarray,
    group_id: np.ndarray,
    group_static: np.ndarray,
    group_rigid: np.ndarray,
) -> dict[str, Any]:
    """observed_means (N, T, 3), forecast_means (N, n, 3), per-Gaussian
    group ids and per-group flags -> the figures (see the module doc)."""
    obs = np.asarray(observed_means, np.float64)
    fc = np.asarray(forecast_means, np.float64)
    last = obs[:, -1]
    rng = np.random.default_rng(0)
    changes, rel_changes = [], []
    still = np.zeros(obs.shape[0], bool)
    for k in range(group_static.size):
        members = np.flatnonzero(group_id == k)
        if members.size == 0:
            continue
        if group_static[k]:
            continue
        if not group_rigid[k]:
            still[members] = still_gaussians(obs[members], STILL_FACTOR)
            continue
        # the rigid body is the members that moved: a still part joined to
        # it is measured as still (below), not as part of the body
        group_still = rigid_group_still(obs[members], STILL_FACTOR)
        still[members] = group_still
        body = members[~group_still]
        c, r = rigid_distance_change(last[body], fc[body], rng)
        changes.append(c)
        rel_changes.append(r)
    disp = np.linalg.norm(fc[still] - last[still, None], axis=-1)
    return {
        "rigid_groups": len(changes),
        "rigid_distance_change": float(np.mean(changes)) if changes else None,
        "rigid_distance_change_rel": float(np.mean(rel_changes)) if rel_changes else None,
        "still_gaussians": int(still.sum()),
        "still_displacement": float(disp.mean()) if disp.size else None,
    }
