"""Initialisation from 2D tracks and depth (Shape-of-Motion recipe, re-derived).

Monocular scenes with depth and 2D tracks (iphone layout):
  1. lift every visible track point with the depth map at its pixel (only
     where the depth is valid and the pixel is foreground); fill the other
     frames by linear interpolation in time (nearest value at the ends);
  2. canonical frame = the observed frame with the most lifted track points;
  3. drop outliers (canonical distance to the median above the 95% quantile);
  4. k-means (B clusters) on the per-step velocity directions of the tracks;
     clusters below `init_min_cluster_fraction` of the tracks are dropped,
     so B can end up smaller than asked;
  5. per cluster and observed frame, a weighted Procrustes fit (roma,
     Kabsch) from the canonical positions to that frame's positions gives
     the basis (rotation as continuous 6D, translation); frames with too
     little weight copy the previous (walking away from the canonical frame);
     time steps without a frame are interpolated linearly;
  6. coefficient logits = scale * exp(-d / length), d = distance to each
     cluster's median canonical point;
  7. a short optimisation fits bases, coefficients and canonical means to the
     3D tracks (3D L1 + basis smoothness + coefficient sparsity), no
     rendering;
  8. fg Gaussians = the fitted tracks + points lifted from the canonical
     frame's fg pixels (coefficients copied from the nearest tracks);
     bg Gaussians = background pixels with valid depth, all frames.
Scales: mean distance to the 3 nearest neighbours (fg clamped to its 5-95%
quantiles); opacity 0.7; colour = pixel colour; rotations random.
"""

from __future__ import annotations

import numpy as np
import torch

from ..errors import MogafError
from ..optim import Adam
from ..representation import blend_bases, matrix_to_rot6d
from .data import TrainData
from .init_common import (
    IDENTITY_6D,
    InitResult,
    _bg_from_depth,
    _use_bg,
    coef_logits_from_centres,
    gaussian_tensors,
    pixel_labels,
    robust_extent,
    sample_pixels,
    unproject,
)
from .interpolation import fill_in_time, interpolate_steps
from .losses import accel_loss, basis_smoothness


def lift_tracks(data: TrainData) -> tuple[np.ndarray, np.ndarray]:
    """World positions (P,F,3) of the track points and where they are valid (P,F)."""
    P, F = data.tracks_xy.shape[:2]
    xyz = np.zeros((P, F, 3), np.float64)
    ok = np.zeros((P, F), bool)
    for f in range(F):
        vis = data.tracks_visible[:, f]
        uv = data.tracks_xy[:, f].astype(np.float64)
        inside = vis & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < data.width) & (uv[:, 1] < data.height)
        if not inside.any():
            continue
        idx = np.flatnonzero(inside)
        d = sample_pixels(data.depth[f], uv[idx])
        v = sample_pixels(data.depth_valid[f], uv[idx]) & (d > 0)
        m = sample_pixels(data.fg_masks[f], uv[idx]) > 0.5
        good = v & m
        idx, d = idx[good], d[good]
        xyz[idx, f] = unproject(uv[idx], d, data.K[f], data.w2c[f])
        ok[idx, f] = True
    return xyz, ok


def procrustes_weights(cluster: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """SoM-style per-point weights (F, n): closer to the cluster median = heavier; 10% farthest ignored."""
    med = np.median(cluster, axis=1, keepdims=True)
    d = np.linalg.norm(cluster - med, axis=-1)
    d = d / np.maximum(np.median(d, axis=1, keepdims=True), 1e-9)
    w = np.exp(-d)
    w = w / (w.mean(axis=1, keepdims=True) + 1e-6)
    w = w * (valid.astype(np.float64) + 1e-6)
    w[d > np.quantile(d, 0.9)] = 0.0
    return w


def rigid_fit(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted Kabsch: R, t minimising sum w |R x + t - y|^2 (roma)."""
    from ..eager_roma import load as load_roma

    roma = load_roma()

    R, t = roma.rigid_points_registration(
        torch.tensor(x, dtype=torch.float64),
        torch.tensor(y, dtype=torch.float64),
        weights=torch.tensor(w, dtype=torch.float64),
    )
    return R.numpy(), t.numpy()


def bases_from_clusters(
    xyz: np.ndarray,
    ok: np.ndarray,
    labels: np.ndarray,
    ids: np.ndarray,
    cano: int,
    frame_tidx: np.ndarray,
    T: int,
    min_weight: float = 3.0,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Per-cluster Procrustes bases at every observed step: rot6d (B,T,6), transl (B,T,3)."""
    F = xyz.shape[1]
    B = len(ids)
    rot_f = np.zeros((B, F, 6))
    tr_f = np.zeros((B, F, 3))
    rot_f[:] = IDENTITY_6D.numpy()
    # frames ordered outwards from the canonical one (its basis is the identity)
    order = np.argsort(np.abs(frame_tidx - frame_tidx[cano]) * F + np.abs(np.arange(F) - cano), kind="stable")
    errs_before, errs_after, skipped = [], [], 0
    for b, cid in enumerate(ids):
        sel = labels == cid
        cl = np.swapaxes(xyz[sel], 0, 1)  # (F, n, 3)
        vv = np.swapaxes(ok[sel], 0, 1)
        w = procrustes_weights(cl, vv)
        done = np.zeros(F, bool)
        for f in order:
            if f == cano:
                done[f] = True
                continue
            ww = w[cano] * w[f]
            if ww.sum() < min_weight:
                # copy from the nearest already-solved frame in time
                cands = np.flatnonzero(done)
                near = cands[np.argmin(np.abs(frame_tidx[cands] - frame_tidx[f]))]
                rot_f[b, f], tr_f[b, f] = rot_f[b, near], tr_f[b, near]
                skipped += 1
            else:
                R, t = rigid_fit(cl[cano], cl[f], ww)
                rot_f[b, f] = matrix_to_rot6d(torch.tensor(R)).numpy()
                tr_f[b, f] = t
                m = ww > 0
                errs_before.append(np.mean(np.linalg.norm(cl[f][m] - cl[cano][m], axis=-1)))
                errs_after.append(np.mean(np.linalg.norm(cl[cano][m] @ R.T + t - cl[f][m], axis=-1)))
            done[f] = True
    # frames -> steps (first frame of a step with the most valid tracks wins)
    rot = np.zeros((B, T, 6))
    tr = np.zeros((B, T, 3))
    have = np.zeros(T, bool)
    counts = ok.sum(axis=0)
    for f in np.argsort(-counts, kind="stable"):
        s = int(frame_tidx[f])
        if not have[s]:
            rot[:, s], tr[:, s], have[s] = rot_f[:, f], tr_f[:, f], True
    rot = interpolate_steps(rot, have)
    tr = interpolate_steps(tr, have)
    info = {
        "procrustes_err_before": float(np.mean(errs_before)) if errs_before else 0.0,
        "procrustes_err_after": float(np.mean(errs_after)) if errs_after else 0.0,
        "procrustes_skipped": int(skipped),
    }
    return rot, tr, info


def velocity_clusters(
    xyz: np.ndarray, times: np.ndarray, num: int, seed: int, min_fraction: float
) -> tuple[np.ndarray, np.ndarray]:
    """k-means on velocity directions (P,F-1,3 flattened). Returns labels (P,) and kept cluster ids."""
    from sklearn.cluster import KMeans

    P = xyz.shape[0]
    order = np.argsort(times, kind="stable")
    x = xyz[:, order]
    v = x[:, 1:] - x[:, :-1]
    speed = np.linalg.norm(v, axis=-1, keepdims=True)
    # soft normalisation: near-static points get short vectors, not random unit ones
    eps = max(float(np.median(speed)) * 0.1, 1e-9)
    feats = (v / (speed + eps)).reshape(P, -1)
    k = max(1, min(num, P))
    km = KMeans(n_clusters=k, n_init=3, random_state=seed).fit(feats)
    labels = km.labels_.astype(np.int64)
    ids, counts = np.unique(labels, return_counts=True)
    keep = ids[counts >= max(2, int(np.ceil(min_fraction * P)))]
    if keep.size == 0:
        keep = ids[np.argmax(counts)][None]
    return labels, keep


def fit_bases_to_tracks(
    means: np.ndarray,
    coef_logits: np.ndarray,
    rot: np.ndarray,
    tr: np.ndarray,
    xyz: np.ndarray,
    ok: np.ndarray,
    frame_tidx: np.ndarray,
    iters: int,
    scale: float,
    smoothness: str = "acceleration",
) -> tuple[np.ndarray, ...]:
    """SoM's initial optimisation: bases, coefficients and canonical means fit the lifted 3D tracks."""
    if iters <= 0:
        return means, coef_logits, rot, tr
    m = torch.tensor(means, dtype=torch.float32, requires_grad=True)
    c = torch.tensor(coef_logits, dtype=torch.float32, requires_grad=True)
    r = torch.tensor(rot, dtype=torch.float32, requires_grad=True)
    t = torch.tensor(tr, dtype=torch.float32, requires_grad=True)
    target = torch.tensor(xyz, dtype=torch.float32)  # (P, F, 3)
    w = torch.tensor(ok, dtype=torch.float32)[..., None]
    ft = torch.tensor(frame_tidx, dtype=torch.int64)
    opt = Adam(
        [
            {"params": [r], "lr": 1e-2},
            {"params": [t], "lr": 3e-2 * scale},
            {"params": [c], "lr": 1e-2},
            {"params": [m], "lr": 1e-3 * scale},
        ]
    )
    gamma = 0.1 ** (1.0 / iters)
    for i in range(iters):
        coefs = torch.softmax(c, dim=-1)
        R, tt = blend_bases(coefs, r[:, ft], t[:, ft])  # (P, F, 3, 3)
        pos = torch.einsum("pfij,pj->pfi", R, m) + tt
        loss = ((pos - target).abs().mean(-1, keepdim=True) * w).sum() / w.sum().clamp_min(1) / scale
        loss = loss + 0.01 * (1 - (coefs**2).sum(-1).mean())
        ws = 0.01 if i < iters * 0.4 else 0.01 + 0.09 * (i - iters * 0.4) / (iters * 0.6)
        loss = loss + ws * basis_smoothness(r, t, scale, smoothness)
        order = torch.argsort(ft, stable=True)
        loss = loss + 0.5 * ws * accel_loss(pos[:, order] / scale)
        opt.zero_grad()
        loss.backward()
        opt.step()
        for g in opt.param_groups:
            g["lr"] *= gamma
    return (
        m.detach().numpy().astype(np.float64),
        c.detach().numpy(),
        r.detach().numpy().astype(np.float64),
        t.detach().numpy().astype(np.float64),
    )


def _init_from_tracks(data: TrainData, params: dict, rng: np.random.Generator, seed: int) -> InitResult:
    T = data.num_timesteps
    xyz, ok = lift_tracks(data)
    good = ok.sum(axis=1) >= 2
    if good.sum() < 8:
        raise MogafError("reconstruction init: fewer than 8 foreground tracks could be lifted with depth")
    xyz, ok = xyz[good], ok[good]
    track_ids = np.flatnonzero(good)
    times = data.tidx.astype(np.float64)
    xyz = fill_in_time(xyz, ok, times)
    cano = int(np.argmax(ok.sum(axis=0))) if params.canonical_frame < 0 else params.canonical_frame
    can = xyz[:, cano]
    dist = np.linalg.norm(can - np.median(can, axis=0), axis=-1)
    inl = dist <= np.quantile(dist, 0.95) if len(dist) > 40 else np.ones(len(dist), bool)
    xyz, ok, can, track_ids = xyz[inl], ok[inl], can[inl], track_ids[inl]

    labels, ids = velocity_clusters(xyz, times, params.num_bases, seed, params.init_min_cluster_fraction)
    keep = np.isin(labels, ids)
    rot, tr, info = bases_from_clusters(xyz, ok, labels, ids, cano, data.tidx, T)
    fg_extent = robust_extent(can)
    centres = np.stack([np.median(can[labels == i], axis=0) for i in ids])
    length = params.init_coef_length * 2 * fg_extent
    logits = coef_logits_from_centres(can, centres, params.init_coef_scale, length)
    # fit tracks (SoM run_initial_optim)
    scale0 = max(fg_extent, 1e-3)
    m_fit, c_fit, rot, tr = fit_bases_to_tracks(
        can[keep],
        logits[keep],
        rot,
        tr,
        xyz[keep],
        ok[keep],
        data.tidx,
        params.init_optim_iters,
        scale0,
        params.smooth_bases,
    )
    info.update(num_tracks=int(keep.sum()), num_clusters=int(len(ids)))
    track_ids = track_ids[keep]

    # fg Gaussians: tracks + dense canonical fg pixels
    n_fg = params.num_fg_init
    n_dense = int(round(n_fg * params.init_fg_dense_fraction))
    n_tr = min(n_fg - n_dense, m_fit.shape[0])
    pick = (
        np.sort(rng.choice(m_fit.shape[0], n_tr, replace=False)) if n_tr < m_fit.shape[0] else np.arange(m_fit.shape[0])
    )
    tr_means, tr_logits = m_fit[pick], c_fit[pick]
    # colours of track points: their pixel in the canonical frame, else in the first frame they were lifted
    tids = track_ids[pick]
    okp = ok[keep][pick]
    first = np.where(okp[:, cano], cano, np.argmax(okp, axis=1))
    colours = np.zeros((len(pick), 3))
    tr_labels = np.zeros(len(pick), np.int64)
    lab_img = data.instance_mask if data.instance_mask is not None else (data.fg_masks > 0.5).astype(np.int64)
    for f in np.unique(first):
        s = first == f
        colours[s] = sample_pixels(data.images[f], data.tracks_xy[tids[s], f])
        tr_labels[s] = sample_pixels(lab_img[f], data.tracks_xy[tids[s], f])
    fgm = (data.fg_masks[cano] > 0.5) & data.depth_valid[cano]
    rr, cc = np.nonzero(fgm)
    n_dense = min(n_fg - n_tr, rr.size)
    dense_means = np.zeros((0, 3))
    dense_cols = np.zeros((0, 3))
    dense_logits = np.zeros((0, tr_logits.shape[1]), np.float32)
    dense_labels = np.zeros(0, np.int64)
    if n_dense > 0:
        sel = np.sort(rng.choice(rr.size, n_dense, replace=False))
        uv = np.stack([cc[sel] + 0.5, rr[sel] + 0.5], axis=1)
        d = data.depth[cano][rr[sel], cc[sel]]
        wp = unproject(uv, d, data.K[cano], data.w2c[cano])
        # canonical space = world at the canonical step only if its bases are the identity;
        # map back through the fitted blend at the canonical step.
        dense_logits = _knn_logits(wp, _posed(m_fit, c_fit, rot, tr, int(data.tidx[cano])), c_fit)
        dense_means = _unpose(wp, dense_logits, rot, tr, int(data.tidx[cano]))
        dense_cols = data.images[cano][rr[sel], cc[sel]]
        dense_labels = pixel_labels(data, cano, rr[sel], cc[sel])
    means = np.concatenate([tr_means, dense_means])
    cols = np.concatenate([colours, dense_cols])
    logits_all = np.concatenate([tr_logits, dense_logits]).astype(np.float32)
    fg = gaussian_tensors(means, cols, rng, params.init_opacity, params.sh_degree, True, logits_all)
    fg["labels"] = torch.tensor(np.concatenate([tr_labels, dense_labels]), dtype=torch.int64)

    bg = None
    bg_pts = np.zeros((0, 3))
    if _use_bg(params, data):
        bg_pts, bg_cols = _bg_from_depth(data, params.num_bg_init, rng)
        if bg_pts.shape[0] >= 4:
            bg = gaussian_tensors(bg_pts, bg_cols, rng, params.init_opacity, params.sh_degree, False)
    scene_scale = robust_extent(np.concatenate([means, bg_pts])) if bg_pts.shape[0] else robust_extent(means)
    info.update(canonical_frame=cano, fg_extent=fg_extent)
    return InitResult(
        fg,
        torch.tensor(rot, dtype=torch.float32),
        torch.tensor(tr, dtype=torch.float32),
        bg,
        scene_scale,
        cano,
        "procrustes",
        info,
    )


def _posed(means: np.ndarray, logits: np.ndarray, rot: np.ndarray, tr: np.ndarray, step: int) -> np.ndarray:
    with torch.no_grad():
        c = torch.softmax(torch.tensor(logits, dtype=torch.float64), -1)
        R, t = blend_bases(
            c, torch.tensor(rot[:, step], dtype=torch.float64), torch.tensor(tr[:, step], dtype=torch.float64)
        )
        return (torch.einsum("nij,nj->ni", R, torch.tensor(means, dtype=torch.float64)) + t).numpy()


def _unpose(points: np.ndarray, logits: np.ndarray, rot: np.ndarray, tr: np.ndarray, step: int) -> np.ndarray:
    with torch.no_grad():
        c = torch.softmax(torch.tensor(logits, dtype=torch.float64), -1)
        R, t = blend_bases(
            c, torch.tensor(rot[:, step], dtype=torch.float64), torch.tensor(tr[:, step], dtype=torch.float64)
        )
        return torch.einsum("nji,nj->ni", R, torch.tensor(points, dtype=torch.float64) - t).numpy()


def _knn_logits(points: np.ndarray, ref_points: np.ndarray, ref_logits: np.ndarray, k: int = 4) -> np.ndarray:
    from sklearn.neighbors import NearestNeighbors

    k = min(k, ref_points.shape[0])
    nn = NearestNeighbors(n_neighbors=k).fit(ref_points)
    d, idx = nn.kneighbors(points)
    w = 1.0 / np.maximum(d, 1e-6)
    w /= w.sum(axis=1, keepdims=True)
    return np.einsum("nk,nkb->nb", w, ref_logits[idx]).astype(np.float32)
