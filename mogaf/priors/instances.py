"""Instances from motion: clustering of 2D tracks, then pixel labels.

Used when the dataset ships no instance masks. Tracks are compared pairwise
on the frames where both are visible (positions sampled every
`cluster_time_stride` frames, or sparser so that at most 64 samples remain):
  d_motion = RMS over common steps of |v_a - v_b| (velocities, px per frame)
  d_space  = mean over common frames |x_a - x_b| (px)
(pairs sharing fewer than 2 steps are unrelated). Tracks are grouped by
average-linkage agglomerative clustering on d_motion, merging only spatial
neighbours (each track linked to those of its `cluster_knn` nearest tracks
by d_space that lie within `cluster_link_radius_px`), until groups differ by more than `cluster_motion_threshold_px`
(or into `num_instances` groups when that is > 0). So an instance is a
spatially connected set of tracks that move alike; two separate objects
moving alike stay apart. At most `cluster_max_tracks` tracks (a seeded
subsample) are clustered; each other track joins the group of the nearest
clustered track that moves like it. Groups with fewer than
`cluster_min_fraction` of the tracks are merged into the neighbouring group
that moves most alike, and at most `max_instances` groups are kept (the
closest are merged). Ids are 1..K by decreasing size.

Each observed frame's foreground pixels take the group of the nearest track
visible in that frame (nearest track at its last known position when none is
visible). Rigidity of such instances is unknown (-1).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from .params import load_settings
from .tracks import Tracks

MAX_TIME_SAMPLES = 64  # the stride grows on long videos to bound the pairwise cost


def _features(tracks: Tracks, stride: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    T = tracks.xy.shape[1]
    stride = max(1, int(stride), int(np.ceil(T / MAX_TIME_SAMPLES)))
    ts = np.arange(0, T, stride)
    X = tracks.xy[:, ts].astype(np.float64)
    V = tracks.visible[:, ts]
    dt = np.diff(ts).astype(np.float64)
    D = np.diff(X, axis=1) / dt[None, :, None] if len(ts) > 1 else np.zeros((len(X), 0, 2))
    DV = V[:, 1:] & V[:, :-1]
    return X, V, D, DV


def _distances(rows: np.ndarray, cols: np.ndarray, feats, chunk: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """(d_motion, d_space) between tracks `rows` and `cols`; inf where unrelated."""
    X, V, D, DV = feats
    dm_out = np.full((len(rows), len(cols)), np.inf)
    ds_out = np.full((len(rows), len(cols)), np.inf)
    Xc, Vc, Dc, DVc = X[cols], V[cols], D[cols], DV[cols]
    for s in range(0, len(rows), chunk):
        r = rows[s : s + chunk]
        common = DV[r][:, None, :] & DVc[None]  # (m, n, S-1)
        nstep = common.sum(-1)
        if D.shape[1]:
            dv = np.linalg.norm(D[r][:, None] - Dc[None], axis=-1)
            dm = np.sqrt(np.where(common, dv**2, 0.0).sum(-1) / np.maximum(nstep, 1))
        else:
            dm = np.zeros(nstep.shape)
        cf = V[r][:, None, :] & Vc[None]
        dx = np.linalg.norm(X[r][:, None] - Xc[None], axis=-1)
        ds = np.where(cf, dx, 0.0).sum(-1) / np.maximum(cf.sum(-1), 1)
        ok = nstep >= 2
        dm_out[s : s + chunk] = np.where(ok, dm, np.inf)
        ds_out[s : s + chunk] = np.where(ok, ds, np.inf)
    return dm_out, ds_out


def _agglomerate(
    dm: np.ndarray, ds: np.ndarray, knn: int, radius: float, threshold: float, n_clusters: int
) -> np.ndarray:
    from scipy.sparse import csr_matrix
    from sklearn.cluster import AgglomerativeClustering

    n = dm.shape[0]
    if n == 1:
        return np.zeros(1, np.int64)
    k = max(1, min(int(knn), n - 1))
    dsn = ds.copy()
    np.fill_diagonal(dsn, np.inf)
    nearest = np.argpartition(dsn, k - 1, axis=1)[:, :k]
    rows = np.repeat(np.arange(n), k)
    cols = nearest.ravel()
    finite = dsn[rows, cols] <= radius  # (inf for tracks never visible together)
    conn = csr_matrix((np.ones(finite.sum()), (rows[finite], cols[finite])), shape=(n, n))
    conn = ((conn + conn.T) > 0).astype(np.float64)
    big = 1e6  # unrelated pairs (no common frames)
    dist = np.where(np.isfinite(dm), dm, big)
    dist = 0.5 * (dist + dist.T)
    np.fill_diagonal(dist, 0.0)
    if n_clusters > 0:
        import warnings

        with warnings.catch_warnings():
            # sklearn links disconnected components itself (with a warning).
            warnings.simplefilter("ignore")
            model = AgglomerativeClustering(
                n_clusters=int(n_clusters), metric="precomputed", linkage="average", connectivity=conn
            )
            return model.fit_predict(dist).astype(np.int64)
    # Spatially separate components never merge: cluster each on its own.
    from scipy.sparse.csgraph import connected_components

    ncomp, comp = connected_components(conn, directed=False)
    labels = np.zeros(n, np.int64)
    next_id = 0
    for c in range(ncomp):
        idx = np.flatnonzero(comp == c)
        if idx.size == 1:
            sub = np.zeros(1, np.int64)
        else:
            model = AgglomerativeClustering(
                n_clusters=None,
                distance_threshold=float(threshold),
                metric="precomputed",
                linkage="average",
                connectivity=conn[idx][:, idx],
            )
            sub = model.fit_predict(dist[np.ix_(idx, idx)]).astype(np.int64)
        labels[idx] = sub + next_id
        next_id += int(sub.max()) + 1
    return labels


def _merge_small(labels: np.ndarray, dm: np.ndarray, min_size: int, max_groups: int) -> np.ndarray:
    """Merge groups below min_size, then the closest groups above max_groups."""
    labels = labels.copy()
    fin = np.where(np.isfinite(dm), dm, np.nan)
    while True:
        ids, counts = np.unique(labels, return_counts=True)
        if len(ids) <= 1:
            return labels
        small = counts.min() < min_size
        if not small and len(ids) <= max_groups:
            return labels
        if small:
            a = ids[np.argmin(counts)]
            cand = [c for c in ids if c != a]
        else:
            # Merge the pair of groups with the smallest mean motion difference.
            a, cand = None, None
        if a is not None:
            scores = []
            for c in cand:
                block = fin[np.ix_(labels == a, labels == c)]
                scores.append(np.nanmean(block) if np.isfinite(block).any() else np.inf)
            labels[labels == a] = cand[int(np.argmin(scores))]
        else:
            best, pair = np.inf, (ids[0], ids[1])
            for i, x in enumerate(ids):
                for y in ids[i + 1 :]:
                    block = fin[np.ix_(labels == x, labels == y)]
                    v = np.nanmean(block) if np.isfinite(block).any() else np.inf
                    if v < best:
                        best, pair = v, (x, y)
            labels[labels == pair[1]] = pair[0]


def cluster_tracks(tracks: Tracks, image_hw: tuple[int, int], params: Mapping[str, Any]) -> np.ndarray:
    """Instance ids 1..K (P,) int64 for the tracks; empty input -> empty output."""
    params = load_settings(params)
    P = tracks.num_tracks
    if P == 0:
        return np.zeros(0, np.int64)
    thr = max(float(params.cluster_motion_threshold_px), 1e-6)
    feats = _features(tracks, int(params.cluster_time_stride))
    rng = np.random.default_rng(int(params.seed))
    cap = max(2, int(params.cluster_max_tracks))
    core = np.sort(rng.choice(P, cap, replace=False)) if cap < P else np.arange(P)
    dm, ds = _distances(core, core, feats)
    core_lab = _agglomerate(
        dm, ds, int(params.cluster_knn), float(params.cluster_link_radius_px), thr, int(params.num_instances)
    )
    min_size = max(1, int(np.ceil(float(params.cluster_min_fraction) * len(core))))
    max_groups = int(params.num_instances) if int(params.num_instances) > 0 else max(1, int(params.max_instances))
    core_lab = _merge_small(core_lab, dm, min_size, max_groups)
    labels = np.zeros(P, np.int64)
    labels[core] = core_lab
    rest = np.setdiff1d(np.arange(P), core)
    for s in range(0, rest.size, 256):
        r = rest[s : s + 256]
        dmr, dsr = _distances(r, core, feats)
        # Nearest clustered track among those moving alike, else the most alike.
        alike = np.where(dmr <= thr, dsr, np.inf)
        best = np.where(np.isfinite(alike).any(1), np.argmin(alike, 1), np.argmin(dmr, 1))
        labels[r] = core_lab[best]
        lonely = ~np.isfinite(dmr).any(1)
        for i in np.flatnonzero(lonely):
            q = tracks.query_index[r[i]]
            d = np.linalg.norm(tracks.xy[core, q] - tracks.xy[r[i], q], axis=1)
            labels[r[i]] = core_lab[int(np.argmin(d))]
    # Ids 1..K by decreasing size (ties: smaller old id first).
    ids, counts = np.unique(labels, return_counts=True)
    order = ids[np.lexsort((ids, -counts))]
    remap = np.zeros(int(ids.max()) + 1, np.int64)
    remap[order] = np.arange(1, len(order) + 1)
    return remap[labels]


def label_pixels(tracks: Tracks, labels: np.ndarray, fg: np.ndarray) -> np.ndarray:
    """(T, H, W) int32: each foreground pixel gets its nearest track's label."""
    T, H, W = fg.shape
    out = np.zeros((T, H, W), np.int32)
    if tracks.num_tracks == 0:
        return out
    for t in range(T):
        ys, xs = np.nonzero(fg[t])
        if ys.size == 0:
            continue
        vis = tracks.visible[:, t]
        sel = np.flatnonzero(vis) if vis.any() else np.arange(tracks.num_tracks)
        tree = cKDTree(tracks.xy[sel, t].astype(np.float64))
        _, nn = tree.query(np.stack([xs + 0.5, ys + 0.5], -1), k=1)
        out[t, ys, xs] = labels[sel[nn]]
    return out
