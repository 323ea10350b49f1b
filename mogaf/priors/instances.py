"""Instances from motion: spectral clustering of 2D tracks, then pixel labels.

Used when the dataset ships no instance masks. Tracks are compared pairwise
on the frames where both are visible (positions sampled every
`cluster_time_stride` frames):
  d_motion = max over common steps |v_a - v_b|   (velocities, px per frame)
  d_space  = mean over common frames |x_a - x_b| (px)
  affinity = exp(-(d_motion / cluster_motion_sigma_px)^2
                 -(d_space / (cluster_spatial_sigma * image diagonal))^2),
0 for pairs sharing fewer than 2 steps. The number of clusters is
`num_instances`, or (0) the largest eigengap of the normalised graph
Laplacian up to `max_instances`; embeddings are clustered with k-means.
At most `cluster_max_tracks` tracks (a seeded subsample) enter the
eigenproblem; the others join the cluster of their most similar clustered
track. Clusters holding fewer than `cluster_min_fraction` of the tracks are
merged into their most similar neighbour cluster. Cluster ids are 1..K by
decreasing size.

Each observed frame's foreground pixels take the cluster of the nearest track
visible in that frame (nearest track at its last known position when none is
visible). Rigidity of such instances is unknown (-1).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from scipy.linalg import eigh
from scipy.spatial import cKDTree
from sklearn.cluster import KMeans

from .tracks import Tracks


def _features(tracks: Tracks, stride: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    T = tracks.xy.shape[1]
    ts = np.arange(0, T, max(1, int(stride)))
    X = tracks.xy[:, ts].astype(np.float64)
    V = tracks.visible[:, ts]
    dt = np.diff(ts).astype(np.float64)
    D = np.diff(X, axis=1) / dt[None, :, None] if len(ts) > 1 else np.zeros((len(X), 0, 2))
    DV = V[:, 1:] & V[:, :-1]
    return X, V, D, DV


def _affinity(rows: np.ndarray, cols: np.ndarray, feats, sig_m: float, sig_s: float, chunk: int = 64) -> np.ndarray:
    X, V, D, DV = feats
    out = np.zeros((len(rows), len(cols)), np.float64)
    Xc, Vc, Dc, DVc = X[cols], V[cols], D[cols], DV[cols]
    for s in range(0, len(rows), chunk):
        r = rows[s : s + chunk]
        common = DV[r][:, None, :] & DVc[None]  # (m, n, S-1)
        nstep = common.sum(-1)
        dv = np.linalg.norm(D[r][:, None] - Dc[None], axis=-1)
        dm = np.where(common, dv, 0.0).max(-1) if dv.shape[-1] else np.zeros(nstep.shape)
        cf = V[r][:, None, :] & Vc[None]
        nf = cf.sum(-1)
        dx = np.linalg.norm(X[r][:, None] - Xc[None], axis=-1)
        ds = np.where(cf, dx, 0.0).sum(-1) / np.maximum(nf, 1)
        w = np.exp(-((dm / sig_m) ** 2) - (ds / sig_s) ** 2)
        w[nstep < 2] = 0.0
        out[s : s + chunk] = w
    return out


def cluster_tracks(tracks: Tracks, image_hw: tuple[int, int], params: Mapping[str, Any]) -> np.ndarray:
    """Cluster ids 1..K (P,) int64 for the tracks; empty input -> empty output."""
    P = tracks.num_tracks
    if P == 0:
        return np.zeros(0, np.int64)
    H, W = image_hw
    sig_m = max(float(params["cluster_motion_sigma_px"]), 1e-6)
    sig_s = max(float(params["cluster_spatial_sigma"]) * float(np.hypot(H, W)), 1e-6)
    feats = _features(tracks, int(params["cluster_time_stride"]))
    rng = np.random.default_rng(int(params["seed"]))
    cap = max(2, int(params["cluster_max_tracks"]))
    core = np.sort(rng.choice(P, cap, replace=False)) if P > cap else np.arange(P)
    A = _affinity(core, core, feats, sig_m, sig_s)
    A = 0.5 * (A + A.T)
    np.fill_diagonal(A, 1.0)
    n = len(core)
    deg = A.sum(1)
    Dm = 1.0 / np.sqrt(deg)
    M = Dm[:, None] * A * Dm[None, :]  # normalised affinity; Laplacian = I - M
    kmax = int(min(max(1, int(params["max_instances"])), n))
    evals, evecs = eigh(M, subset_by_index=[n - min(kmax + 1, n), n - 1])
    evals, evecs = evals[::-1], evecs[:, ::-1]  # largest first = smallest Laplacian eigenvalues
    k = int(params["num_instances"])
    if k <= 0:
        lap = 1.0 - evals
        gaps = np.diff(lap)[:kmax] if len(lap) > 1 else np.zeros(0)
        k = int(np.argmax(gaps)) + 1 if gaps.size and gaps.max() > 1e-3 else 1
    k = max(1, min(k, kmax))
    if k == 1:
        core_lab = np.zeros(n, np.int64)
    else:
        emb = evecs[:, :k]
        emb = emb / np.maximum(np.linalg.norm(emb, axis=1, keepdims=True), 1e-12)
        core_lab = KMeans(k, n_init=10, random_state=int(params["seed"])).fit_predict(emb).astype(np.int64)
    # Merge clusters that are too small into their most similar neighbour.
    min_size = max(1, int(np.ceil(float(params["cluster_min_fraction"]) * n)))
    while True:
        ids, counts = np.unique(core_lab, return_counts=True)
        if len(ids) <= 1 or counts.min() >= min_size:
            break
        small = ids[np.argmin(counts)]
        members = core_lab == small
        others = [c for c in ids if c != small]
        score = [A[np.ix_(members, core_lab == c)].sum() for c in others]
        core_lab[members] = others[int(np.argmax(score))]
    labels = np.zeros(P, np.int64)
    labels[core] = core_lab
    rest = np.setdiff1d(np.arange(P), core)
    if rest.size:
        Ar = _affinity(rest, core, feats, sig_m, sig_s)
        best = Ar.argmax(1)
        labels[rest] = core_lab[best]
        # No shared frames with any clustered track: nearest at the query frame.
        lonely = Ar.max(1) <= 0
        if lonely.any():
            for i in np.flatnonzero(lonely):
                q = tracks.query_index[rest[i]]
                d = np.linalg.norm(tracks.xy[core, q] - tracks.xy[rest[i], q], axis=1)
                labels[rest[i]] = core_lab[int(np.argmin(d))]
    # Ids 1..K by decreasing size (ties: smaller old id first).
    ids, counts = np.unique(labels, return_counts=True)
    order = ids[np.lexsort((ids, -counts))]
    remap = {int(old): new + 1 for new, old in enumerate(order)}
    return np.array([remap[int(v)] for v in labels], np.int64)


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
