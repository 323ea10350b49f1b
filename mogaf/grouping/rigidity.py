"""Rigidity (tau_k) and static flags of groups.

Rigidity decides which motion constraint a group gets (paper Sec.
"Group-wise Gaussian Motion Optimization"). The paper takes it from the
grounded segmentation; here the order is:
  1. `rigid_override` in the grouping parameters ("config");
  2. the identity's label in priors.h5 (instances/rigid != -1), with the
     source recorded there ("label" unless it says "config");
  3. an estimate from the group's own observed trajectories ("estimated"):
     the best rigid fit canonical -> deformed means at every observed time
     (weighted Procrustes, mogaf.rigid_fit); relative residual =
     RMS residual over all times and members / RMS distance of the
     deformed members to their centroid; rigid iff below
     `rigidity_threshold`. Groups with fewer than 3 members, or that do
     not move, come out rigid (their residual is ~0).

Static groups: per-Gaussian displacement = max over observed steps of the
distance to the first observed position; a group is static when the
`static_quantile` quantile of its members' displacement is below
`static_threshold` x scene extent (robust bounding-box diagonal of all
foreground trajectories). The scene is static when no foreground Gaussian
moves more than that (the maximum, not a quantile).
"""

from __future__ import annotations

import numpy as np

from ..rigid_fit import fit_residual
from .params import load_settings

VALID_SOURCES = ("label", "config", "estimated")


def scene_extent(trajectories: np.ndarray, max_points: int = 200_000, seed: int = 0) -> float:
    """Robust bbox diagonal (1st-99th percentile per axis) of (N,T,3) positions."""
    pts = np.asarray(trajectories, dtype=np.float64).reshape(-1, 3)
    if pts.shape[0] == 0:
        return 0.0
    if pts.shape[0] > max_points:
        rng = np.random.default_rng(seed)
        pts = pts[rng.choice(pts.shape[0], max_points, replace=False)]
    lo, hi = np.percentile(pts, [1.0, 99.0], axis=0)
    return float(np.linalg.norm(hi - lo))


def displacement(trajectories: np.ndarray) -> np.ndarray:
    """(N,) max over time of |x_t - x_first| for (N,T,3) trajectories."""
    tr = np.asarray(trajectories, dtype=np.float64)
    if tr.shape[0] == 0 or tr.shape[1] == 0:
        return np.zeros(tr.shape[0])
    return np.linalg.norm(tr - tr[:, :1], axis=-1).max(axis=1)


def static_threshold_abs(extent: float, params: dict) -> float:
    return float(load_settings(params).static_threshold) * max(float(extent), 0.0)


def is_static_scene(disp: np.ndarray, extent: float, params: dict) -> bool:
    if disp.size == 0:
        return True
    return bool(disp.max() <= static_threshold_abs(extent, params))


def two_class_threshold(values: np.ndarray) -> float:
    """Otsu's threshold of 1-D values: the cut between sorted neighbours that
    maximises the between-class variance (the midpoint of that pair)."""
    x = np.sort(np.asarray(values, dtype=np.float64))
    n = x.size
    if n < 2:
        return float(x[0]) if n else 0.0
    i = np.arange(1, n)
    csum = np.cumsum(x)
    mean_low = csum[:-1] / i
    mean_high = (csum[-1] - csum[:-1]) / (n - i)
    between = (i / n) * (1 - i / n) * (mean_low - mean_high) ** 2
    k = int(np.argmax(between))
    return float(0.5 * (x[k] + x[k + 1]))


def still_members(positions: np.ndarray, neighbours: int, ratio: float, min_fraction: float) -> np.ndarray:
    """(G,) the members of a group that stay still while the others move, or
    none. positions (G, T, 3) observed. A member's motion is the log of its
    largest displacement from its first position, averaged over its
    `neighbours` nearest members at the last step (a reconstruction's jitter
    is not spatially coherent, a moving part is); the two classes are cut at
    Otsu's threshold and kept where each holds min_fraction of the group and
    the moving class's median motion is `ratio` times the still class's."""
    pos = np.asarray(positions, dtype=np.float64)
    G = pos.shape[0]
    none = np.zeros(G, bool)
    if G < 4 or pos.shape[1] < 2:
        return none
    from scipy.spatial import cKDTree

    motion = np.log(np.maximum(displacement(pos), 1e-12))
    k = min(int(neighbours), G)
    nearest = cKDTree(pos[:, -1]).query(pos[:, -1], k=k)[1].reshape(G, k)
    smooth = motion[nearest].mean(axis=1)
    still = smooth <= two_class_threshold(smooth)
    n_still = int(still.sum())
    if min(n_still, G - n_still) < min_fraction * G:
        return none
    if np.median(smooth[~still]) - np.median(smooth[still]) < np.log(ratio):
        return none
    return still


def split_still_members(
    trajectories: np.ndarray,
    group_id: np.ndarray,
    group_instance: np.ndarray,
    label_rigid: np.ndarray,
    settings,
) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Give the still members of a group whose other members move a group of
    their own (still_members), so that they are held still whatever the
    moving part does.

    trajectories (N, T, 3), group_id (N,) in 0..K-1, group_instance (K,)
    index into the instance table, label_rigid (J,) its rigid labels (1, 0,
    -1 unknown); settings.split_still_members "never" | "unlabelled" (groups
    whose label is unknown) | "not_rigid" (unknown or non-rigid). Returns the
    new group ids, the groups' instance indices (each split part appended
    after the K groups, with its parent's identity) and the parent of each
    appended group.
    """
    group_id = np.asarray(group_id, dtype=np.int64).copy()
    group_instance = np.asarray(group_instance, dtype=np.int64)
    mode = settings.split_still_members
    if mode == "never":
        return group_id, group_instance, []
    allowed = (-1,) if mode == "unlabelled" else (-1, 0)
    parents: list[int] = []
    for k in range(group_instance.size):
        j = int(group_instance[k])
        if (int(label_rigid[j]) if j >= 0 else -1) not in allowed:
            continue
        members = np.flatnonzero(group_id == k)
        still = still_members(
            trajectories[members],
            int(settings.split_neighbors),
            float(settings.split_motion_ratio),
            float(settings.split_min_fraction),
        )
        if not still.any():
            continue
        group_id[members[still]] = group_instance.size + len(parents)
        parents.append(k)
    return group_id, np.r_[group_instance, group_instance[parents]].astype(np.int64), parents


def group_displacement(disp: np.ndarray, group_id: np.ndarray, num_groups: int, quantile: float) -> np.ndarray:
    out = np.zeros(num_groups)
    for k in range(num_groups):
        d = disp[group_id == k]
        if d.size:
            out[k] = float(np.quantile(d, quantile))
    return out


def relative_rigid_residual(
    canonical: np.ndarray, trajectories: np.ndarray, max_points: int = 4096, seed: int = 0
) -> float:
    """Relative RMS residual of the best per-time rigid fit.

    canonical (P,3), trajectories (P,T,3). 0 when the set is rigid.
    """
    x = np.asarray(canonical, dtype=np.float64)
    y = np.asarray(trajectories, dtype=np.float64)
    P = x.shape[0]
    if P < 3 or y.shape[1] == 0:
        return 0.0
    if max_points < P:
        rng = np.random.default_rng(seed)
        idx = np.sort(rng.choice(P, max_points, replace=False))
        x, y = x[idx], y[idx]
    yt = np.transpose(y, (1, 0, 2))  # (T,P,3)
    ms = fit_residual(x, yt, squared=True)  # (T,)
    rms = float(np.sqrt(ms.mean()))
    spread = float(np.sqrt(((yt - yt.mean(axis=1, keepdims=True)) ** 2).sum(-1).mean()))
    if spread <= 0.0:
        return 0.0
    return rms / spread


def estimate_rigid(
    canonical: np.ndarray, trajectories: np.ndarray, threshold: float, max_points: int = 4096, seed: int = 0
) -> tuple[bool, float]:
    """(is_rigid, relative residual) for one group's observed trajectories."""
    r = relative_rigid_residual(canonical, trajectories, max_points, seed)
    return bool(r < threshold), r


def _override_for(override: dict, instance_id: int, name: str):
    if not override:
        return None
    for key in (name, str(instance_id), instance_id):
        if key in override:
            return int(bool(override[key]))
    return None


def decide_rigidity(
    group_instance: np.ndarray,
    table,
    canonical: np.ndarray,
    trajectories: np.ndarray,
    group_id: np.ndarray,
    params: dict,
) -> tuple[np.ndarray, list[str], np.ndarray]:
    """Rigid flag, its source and the estimated relative residual per group.

    group_instance (K,) indexes the InstanceTable (-1: no identity). The
    residual is -1 where no estimate was needed.
    """
    K = group_instance.size
    rigid = np.zeros(K, dtype=np.int8)
    source: list[str] = []
    residual = np.full(K, -1.0)
    params = load_settings(params)
    override = params.rigid_override or {}
    for k in range(K):
        j = int(group_instance[k])
        inst_id = int(table.ids[j]) if j >= 0 else -1
        name = table.names[j] if j >= 0 else ""
        flag = _override_for(override, inst_id, name)
        if flag is not None:
            rigid[k] = flag
            source.append("config")
            continue
        if j >= 0 and int(table.rigid[j]) in (0, 1):
            rigid[k] = int(table.rigid[j])
            src = table.rigid_source[j] if j < len(table.rigid_source) else "label"
            source.append(src if src in ("label", "config") else "label")
            continue
        members = np.flatnonzero(group_id == k)
        ok, r = estimate_rigid(
            canonical[members],
            trajectories[members],
            float(params.rigidity_threshold),
            int(params.rigidity_max_points),
            int(params.seed),
        )
        rigid[k] = int(ok)
        residual[k] = r
        source.append("estimated")
    return rigid, source, residual
