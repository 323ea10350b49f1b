"""Initialisation of the 4D Gaussians (Shape-of-Motion recipe, re-derived).

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

Scenes without depth (D-NeRF layout): candidates are drawn along the rays of
the canonical frame's fg pixels inside the volume (the dataset point cloud's
bounding box if any, else that of the camera centres) and kept if they fall
in the (dilated) fg masks of most frames within a few time steps of the
canonical one (a short-window visual hull); bases start at identity and
coefficients come from k-means on the canonical positions. Optional bg:
points of the volume that project outside every fg mask.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ..camera import camera_centers
from ..errors import MogafError
from ..representation import matrix_to_rot6d, rot6d_to_matrix
from .data import TrainData
from .losses import accel_loss, basis_smoothness
from .model import num_sh_rest


@dataclass
class InitResult:
    fg: dict[str, torch.Tensor]
    rot6d: torch.Tensor  # (B, T, 6)
    transl: torch.Tensor  # (B, T, 3)
    bg: dict[str, torch.Tensor] | None
    scene_scale: float
    canonical_frame: int
    motion_source: str  # "procrustes" (3D tracks), "silhouette" (fit to masks) or "identity"
    info: dict[str, Any] = field(default_factory=dict)


IDENTITY_6D = torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0])


# ------------------------------------------------------------------ geometry helpers
def unproject(uv: np.ndarray, depth: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> np.ndarray:
    """Pixels (M,2) (+0.5 convention) with z-depth (M,) to world points (M,3)."""
    Kinv = np.linalg.inv(K)
    rays = np.concatenate([uv, np.ones((uv.shape[0], 1))], axis=1) @ Kinv.T
    cam = rays * depth[:, None]
    R, t = w2c[:3, :3], w2c[:3, 3]
    return (cam - t) @ R  # R^T (cam - t)


def project(points: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    cam = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[:, 2]
    uvw = cam @ K.T
    uv = uvw[:, :2] / np.where(np.abs(z) < 1e-9, 1e-9, z)[:, None]
    return uv, z


def knn_scale(points: np.ndarray, k: int = 3, clamp: bool = True) -> np.ndarray:
    """Mean distance to the k nearest neighbours (SoM's initial Gaussian size)."""
    from sklearn.neighbors import NearestNeighbors

    n = points.shape[0]
    if n <= 1:
        return np.full(n, 0.01, np.float64)
    kk = min(k, n - 1)
    nn = NearestNeighbors(n_neighbors=kk + 1).fit(points)
    d, _ = nn.kneighbors(points)
    s = d[:, 1:].mean(axis=1)
    s = np.maximum(s, 1e-6)
    if clamp and n > 20:
        s = np.clip(s, np.quantile(s, 0.05), np.quantile(s, 0.95))
    return s


def sample_pixels(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Nearest-pixel values of (H, W, ...) at continuous coordinates uv (M,2)."""
    H, W = img.shape[:2]
    c = np.clip(np.floor(uv[:, 0]).astype(np.int64), 0, W - 1)
    r = np.clip(np.floor(uv[:, 1]).astype(np.int64), 0, H - 1)
    return img[r, c]


def random_quats(n: int, rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True).clip(1e-12)
    return np.where(q[:, :1] < 0, -q, q)


def color_logits(rgb: np.ndarray) -> np.ndarray:
    c = np.clip(rgb, 0.02, 0.98)
    return np.log(c / (1 - c))


def logit(p: float) -> float:
    return float(np.log(p / (1 - p)))


def robust_extent(points: np.ndarray) -> float:
    """Half of the largest 5-95% quantile range over the axes (SoM's scene scale)."""
    if points.shape[0] < 2:
        return 1.0
    lo, hi = np.quantile(points, 0.05, axis=0), np.quantile(points, 0.95, axis=0)
    e = float(np.max(hi - lo) / 2.0)
    return e if e > 1e-6 else 1.0


def coef_logits_from_centres(points: np.ndarray, centres: np.ndarray, scale: float, length: float) -> np.ndarray:
    d = np.linalg.norm(points[:, None] - centres[None], axis=-1)
    return (scale * np.exp(-d / max(length, 1e-9))).astype(np.float32)


def gaussian_tensors(means: np.ndarray, colors: np.ndarray, rng: np.random.Generator, opacity: float, sh_degree: int,
                     clamp_scale: bool, coef_logits: np.ndarray | None = None) -> dict[str, torch.Tensor]:
    n = means.shape[0]
    scales = knn_scale(means, 3, clamp=clamp_scale)
    out = {
        "means": torch.tensor(means, dtype=torch.float32),
        "quats": torch.tensor(random_quats(n, rng), dtype=torch.float32),
        "log_scales": torch.tensor(np.log(np.repeat(scales[:, None], 3, axis=1)), dtype=torch.float32),
        "opacity_logits": torch.full((n,), logit(opacity), dtype=torch.float32),
        "color_logits": torch.tensor(color_logits(colors), dtype=torch.float32),
    }
    if sh_degree > 0:
        out["sh_rest"] = torch.zeros((n, num_sh_rest(sh_degree), 3), dtype=torch.float32)
    if coef_logits is not None:
        out["motion_coef_logits"] = torch.tensor(coef_logits, dtype=torch.float32)
    return out


# ------------------------------------------------------------------ tracks
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


def fill_in_time(xyz: np.ndarray, ok: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Linear interpolation of invalid entries over frame times (nearest at the ends)."""
    out = xyz.copy()
    order = np.argsort(times, kind="stable")
    tt = times[order].astype(np.float64)
    for p in range(xyz.shape[0]):
        okp = ok[p, order]
        if okp.all() or not okp.any():
            continue
        for d in range(3):
            vals = xyz[p, order, d]
            out[p, order, d] = np.interp(tt, tt[okp], vals[okp])
    return out


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
    import roma

    R, t = roma.rigid_points_registration(torch.tensor(x, dtype=torch.float64), torch.tensor(y, dtype=torch.float64),
                                          weights=torch.tensor(w, dtype=torch.float64))
    return R.numpy(), t.numpy()


def interpolate_steps(values: np.ndarray, have: np.ndarray) -> np.ndarray:
    """(B, T, D) values defined where have (T,) is True; linear in between, nearest at the ends."""
    if have.all():
        return values
    if not have.any():
        raise MogafError("reconstruction init: no observed time step has a frame")
    T = values.shape[1]
    steps = np.arange(T)
    out = values.copy()
    for b in range(values.shape[0]):
        for d in range(values.shape[2]):
            out[b, :, d] = np.interp(steps, steps[have], values[b, have, d])
    return out


def gap_interpolation(num_steps: int, knots: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Steps without a frame, and the (gaps, K) matrix that fills them from the K knot steps.

    Natural cubic spline through the knots (linear in the knot values) inside
    [first knot, last knot], the end knot's value outside. None if every step
    is a knot.
    """
    from scipy.interpolate import CubicSpline

    knots = np.unique(np.asarray(knots, dtype=np.int64))
    gaps = np.setdiff1d(np.arange(num_steps), knots)
    if gaps.size == 0:
        return None
    K = knots.size
    M = np.zeros((gaps.size, K))
    inside = (gaps > knots[0]) & (gaps < knots[-1])
    if K >= 3:
        cs = CubicSpline(knots.astype(float), np.eye(K), axis=0, bc_type="natural")
        M[inside] = cs(gaps[inside].astype(float))
    elif K == 2:
        w = (gaps[inside] - knots[0]) / (knots[1] - knots[0])
        M[inside, 0], M[inside, 1] = 1 - w, w
    M[gaps <= knots[0], 0] = 1.0
    M[gaps >= knots[-1], K - 1] = 1.0
    return gaps, M


def bases_from_clusters(xyz: np.ndarray, ok: np.ndarray, labels: np.ndarray, ids: np.ndarray, cano: int,
                        frame_tidx: np.ndarray, T: int, min_weight: float = 3.0) -> tuple[np.ndarray, np.ndarray, dict]:
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


def velocity_clusters(xyz: np.ndarray, times: np.ndarray, num: int, seed: int, min_fraction: float) -> tuple[np.ndarray, np.ndarray]:
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


def fit_bases_to_tracks(means: np.ndarray, coef_logits: np.ndarray, rot: np.ndarray, tr: np.ndarray, xyz: np.ndarray,
                        ok: np.ndarray, frame_tidx: np.ndarray, iters: int, scale: float) -> tuple[np.ndarray, ...]:
    """SoM's initial optimisation: bases, coefficients and canonical means fit the lifted 3D tracks."""
    from ..representation import blend_bases

    if iters <= 0:
        return means, coef_logits, rot, tr
    m = torch.tensor(means, dtype=torch.float32, requires_grad=True)
    c = torch.tensor(coef_logits, dtype=torch.float32, requires_grad=True)
    r = torch.tensor(rot, dtype=torch.float32, requires_grad=True)
    t = torch.tensor(tr, dtype=torch.float32, requires_grad=True)
    target = torch.tensor(xyz, dtype=torch.float32)  # (P, F, 3)
    w = torch.tensor(ok, dtype=torch.float32)[..., None]
    ft = torch.tensor(frame_tidx, dtype=torch.int64)
    opt = torch.optim.Adam([
        {"params": [r], "lr": 1e-2},
        {"params": [t], "lr": 3e-2 * scale},
        {"params": [c], "lr": 1e-2},
        {"params": [m], "lr": 1e-3 * scale},
    ])
    gamma = 0.1 ** (1.0 / iters)
    for i in range(iters):
        coefs = torch.softmax(c, dim=-1)
        R, tt = blend_bases(coefs, r[:, ft], t[:, ft])  # (P, F, 3, 3)
        pos = torch.einsum("pfij,pj->pfi", R, m) + tt
        loss = ((pos - target).abs().mean(-1, keepdim=True) * w).sum() / w.sum().clamp_min(1) / scale
        loss = loss + 0.01 * (1 - (coefs**2).sum(-1).mean())
        ws = 0.01 if i < iters * 0.4 else 0.01 + 0.09 * (i - iters * 0.4) / (iters * 0.6)
        loss = loss + ws * basis_smoothness(r, t, scale)
        order = torch.argsort(ft, stable=True)
        loss = loss + 0.5 * ws * accel_loss(pos[:, order] / scale)
        opt.zero_grad()
        loss.backward()
        opt.step()
        for g in opt.param_groups:
            g["lr"] *= gamma
    return (m.detach().numpy().astype(np.float64), c.detach().numpy(), r.detach().numpy().astype(np.float64),
            t.detach().numpy().astype(np.float64))


# ------------------------------------------------------------------ monocular init
def _init_from_tracks(data: TrainData, params: dict, rng: np.random.Generator, seed: int) -> InitResult:
    F, T = data.num_frames, data.num_timesteps
    xyz, ok = lift_tracks(data)
    good = ok.sum(axis=1) >= 2
    if good.sum() < 8:
        raise MogafError("reconstruction init: fewer than 8 foreground tracks could be lifted with depth")
    xyz, ok = xyz[good], ok[good]
    track_ids = np.flatnonzero(good)
    times = data.tidx.astype(np.float64)
    xyz = fill_in_time(xyz, ok, times)
    cano = int(np.argmax(ok.sum(axis=0))) if params["canonical_frame"] < 0 else params["canonical_frame"]
    can = xyz[:, cano]
    dist = np.linalg.norm(can - np.median(can, axis=0), axis=-1)
    inl = dist <= np.quantile(dist, 0.95) if len(dist) > 40 else np.ones(len(dist), bool)
    xyz, ok, can, track_ids = xyz[inl], ok[inl], can[inl], track_ids[inl]

    labels, ids = velocity_clusters(xyz, times, params["num_bases"], seed, params["init_min_cluster_fraction"])
    keep = np.isin(labels, ids)
    rot, tr, info = bases_from_clusters(xyz, ok, labels, ids, cano, data.tidx, T)
    fg_extent = robust_extent(can)
    centres = np.stack([np.median(can[labels == i], axis=0) for i in ids])
    length = params["init_coef_length"] * 2 * fg_extent
    logits = coef_logits_from_centres(can, centres, params["init_coef_scale"], length)
    # fit tracks (SoM run_initial_optim)
    scale0 = max(fg_extent, 1e-3)
    m_fit, c_fit, rot, tr = fit_bases_to_tracks(can[keep], logits[keep], rot, tr, xyz[keep], ok[keep], data.tidx,
                                               params["init_optim_iters"], scale0)
    info.update(num_tracks=int(keep.sum()), num_clusters=int(len(ids)))
    track_ids = track_ids[keep]

    # fg Gaussians: tracks + dense canonical fg pixels
    n_fg = params["num_fg_init"]
    n_dense = int(round(n_fg * params["init_fg_dense_fraction"]))
    n_tr = min(n_fg - n_dense, m_fit.shape[0])
    pick = np.sort(rng.choice(m_fit.shape[0], n_tr, replace=False)) if n_tr < m_fit.shape[0] else np.arange(m_fit.shape[0])
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
    fg = gaussian_tensors(means, cols, rng, params["init_opacity"], params["sh_degree"], True, logits_all)
    fg["labels"] = torch.tensor(np.concatenate([tr_labels, dense_labels]), dtype=torch.int64)

    bg = None
    bg_pts = np.zeros((0, 3))
    if _use_bg(params, data):
        bg_pts, bg_cols = _bg_from_depth(data, params["num_bg_init"], rng)
        if bg_pts.shape[0] >= 4:
            bg = gaussian_tensors(bg_pts, bg_cols, rng, params["init_opacity"], params["sh_degree"], False)
    scene_scale = robust_extent(np.concatenate([means, bg_pts])) if bg_pts.shape[0] else robust_extent(means)
    info.update(canonical_frame=cano, fg_extent=fg_extent)
    return InitResult(fg, torch.tensor(rot, dtype=torch.float32), torch.tensor(tr, dtype=torch.float32), bg,
                      scene_scale, cano, "procrustes", info)


def _posed(means: np.ndarray, logits: np.ndarray, rot: np.ndarray, tr: np.ndarray, step: int) -> np.ndarray:
    from ..representation import blend_bases

    with torch.no_grad():
        c = torch.softmax(torch.tensor(logits, dtype=torch.float64), -1)
        R, t = blend_bases(c, torch.tensor(rot[:, step], dtype=torch.float64), torch.tensor(tr[:, step], dtype=torch.float64))
        return (torch.einsum("nij,nj->ni", R, torch.tensor(means, dtype=torch.float64)) + t).numpy()


def _unpose(points: np.ndarray, logits: np.ndarray, rot: np.ndarray, tr: np.ndarray, step: int) -> np.ndarray:
    from ..representation import blend_bases

    with torch.no_grad():
        c = torch.softmax(torch.tensor(logits, dtype=torch.float64), -1)
        R, t = blend_bases(c, torch.tensor(rot[:, step], dtype=torch.float64), torch.tensor(tr[:, step], dtype=torch.float64))
        return torch.einsum("nji,nj->ni", R, torch.tensor(points, dtype=torch.float64) - t).numpy()


def _knn_logits(points: np.ndarray, ref_points: np.ndarray, ref_logits: np.ndarray, k: int = 4) -> np.ndarray:
    from sklearn.neighbors import NearestNeighbors

    k = min(k, ref_points.shape[0])
    nn = NearestNeighbors(n_neighbors=k).fit(ref_points)
    d, idx = nn.kneighbors(points)
    w = 1.0 / np.maximum(d, 1e-6)
    w /= w.sum(axis=1, keepdims=True)
    return np.einsum("nk,nkb->nb", w, ref_logits[idx]).astype(np.float32)


def _use_bg(params: dict, data: TrainData) -> bool:
    mode = params["background_gaussians"]
    if mode == "auto":
        return data.layout == "iphone" and params["num_bg_init"] > 0
    return mode == "yes" and params["num_bg_init"] > 0


def _bg_from_depth(data: TrainData, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    F = data.num_frames
    pts, cols = [], []
    per = int(np.ceil(n / F))
    for f in range(F):
        m = (data.fg_masks[f] < 0.5) & data.depth_valid[f]
        rr, cc = np.nonzero(m)
        if rr.size == 0:
            continue
        sel = np.sort(rng.choice(rr.size, min(per, rr.size), replace=False))
        uv = np.stack([cc[sel] + 0.5, rr[sel] + 0.5], axis=1)
        pts.append(unproject(uv, data.depth[f][rr[sel], cc[sel]], data.K[f], data.w2c[f]))
        cols.append(data.images[f][rr[sel], cc[sel]])
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 3))
    P, C = np.concatenate(pts), np.concatenate(cols)
    if P.shape[0] > n:
        sel = np.sort(rng.choice(P.shape[0], n, replace=False))
        P, C = P[sel], C[sel]
    return P, C


# ------------------------------------------------------------------ init without tracks
def _volume_box(data: TrainData) -> tuple[np.ndarray, np.ndarray]:
    if data.point_cloud is not None and len(data.point_cloud) >= 8:
        p = np.asarray(data.point_cloud[:, :3], dtype=np.float64)
        lo, hi = p.min(0), p.max(0)
    else:
        c = camera_centers(data.w2c)
        lo, hi = c.min(0), c.max(0)
        pad = 0.05 * np.max(hi - lo) + 1e-3
        lo, hi = lo - pad, hi + pad
    return lo, hi


def _dilate(mask: np.ndarray, r: int) -> np.ndarray:
    if r <= 0:
        return mask
    import cv2

    k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), k) > 0


def _window_frames(data: TrainData, cano: int, half: int) -> np.ndarray:
    dt = np.abs(data.tidx - data.tidx[cano])
    sel = np.flatnonzero(dt <= half)
    if sel.size < 4:
        sel = np.argsort(dt, kind="stable")[: min(4, data.num_frames)]
    return sel


def pixel_labels(data: TrainData, f: int, rr: np.ndarray, cc: np.ndarray) -> np.ndarray:
    """Instance id of pixels (rows, cols) of frame f (1 for plain foreground when no instance masks)."""
    if data.instance_mask is not None:
        return data.instance_mask[f][rr, cc].astype(np.int64)
    return (data.fg_masks[f][rr, cc] > 0.5).astype(np.int64)


def carve_points(data: TrainData, cano: int, params: dict, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points on the rays of the canonical frame's fg pixels that stay in nearby frames' fg masks.

    Returns points (M,3), colours (M,3) and instance labels (M,).
    """
    lo, hi = _volume_box(data)
    fgm = data.fg_masks[cano] > 0.5
    rr, cc = np.nonzero(fgm)
    if rr.size == 0:
        raise MogafError("reconstruction init: the canonical frame has no foreground pixel")
    n_cand = params["carve_candidates"]
    pix = rng.integers(0, rr.size, size=n_cand)
    uv = np.stack([cc[pix] + rng.random(n_cand), rr[pix] + rng.random(n_cand)], axis=1)
    K, w2c = data.K[cano], data.w2c[cano]
    dirs_cam = np.concatenate([uv, np.ones((n_cand, 1))], axis=1) @ np.linalg.inv(K).T
    R, t = w2c[:3, :3], w2c[:3, 3]
    origin = -R.T @ t
    dirs = dirs_cam @ R  # world, z-depth units
    # ray / box intersection in z-depth units
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (lo[None] - origin[None]) / dirs
        t1 = (hi[None] - origin[None]) / dirs
    tmin = np.nanmax(np.minimum(t0, t1), axis=1)
    tmax = np.nanmin(np.maximum(t0, t1), axis=1)
    tmin = np.maximum(tmin, 1e-3)
    hit = tmax > tmin
    z = tmin + rng.random(n_cand) * (tmax - tmin)
    pts = origin[None] + dirs * z[:, None]
    pts, pix = pts[hit], pix[hit]
    frames = [f for f in _window_frames(data, cano, params["carve_window"]) if f != cano]
    votes = np.zeros(pts.shape[0])
    seen = np.zeros(pts.shape[0])
    lab_img = data.instance_mask if data.instance_mask is not None else (data.fg_masks > 0.5).astype(np.int64)
    n_lab = int(lab_img.max()) + 1
    label_votes = np.zeros((pts.shape[0], n_lab))
    label_votes[np.arange(pts.shape[0]), pixel_labels(data, cano, rr[pix], cc[pix])] += 1.0
    for f in frames:
        m = _dilate(data.fg_masks[f] > 0.5, params["carve_dilate"])
        uvf, zf = project(pts, data.K[f], data.w2c[f])
        inside = (zf > 0) & (uvf[:, 0] >= 0) & (uvf[:, 1] >= 0) & (uvf[:, 0] < data.width) & (uvf[:, 1] < data.height)
        seen += inside
        uvs = np.where(inside[:, None], uvf, 0.0)
        votes += inside & sample_pixels(m, uvs)
        lab = sample_pixels(lab_img[f], uvs)
        np.add.at(label_votes, (np.flatnonzero(inside), lab[inside]), 1.0)
    frac = votes / np.maximum(seen, 1)
    keep = (seen > 0) & (frac >= params["carve_min_fraction"])
    if keep.sum() < 64:  # too strict for this motion: keep the best-supported half
        keep = frac >= np.quantile(frac, 0.5)
    colours = data.images[cano][rr[pix[keep]], cc[pix[keep]]]
    # a point behind the first surface of the canonical ray may belong to another instance:
    # majority label over the canonical and window frames (background votes ignored)
    label_votes[:, 0] = 0
    labels = np.argmax(label_votes[keep], axis=1).astype(np.int64)
    none = label_votes[keep].max(axis=1) <= 0
    labels[none] = pixel_labels(data, cano, rr[pix[keep]], cc[pix[keep]])[none]
    return pts[keep], colours, labels


def instance_aware_coefs(points: np.ndarray, labels: np.ndarray, num_bases: int, scale: float, length: float,
                         seed: int) -> np.ndarray:
    """Coefficient logits from k-means centres; centres never straddle instances.

    Bases are shared out among the instances in proportion to their points
    (at least one each, while there are enough bases); a point's logits are
    scale * (1 + exp(-d / length)) for the centres of its own instance and 0
    for the others (plain k-means + distance when there are more instances
    than bases or no labels).
    """
    from sklearn.cluster import KMeans

    ids, counts = np.unique(labels, return_counts=True)
    B = max(1, min(num_bases, points.shape[0]))
    if len(ids) <= 1 or len(ids) > B:
        km = KMeans(n_clusters=B, n_init=3, random_state=seed).fit(points)
        return coef_logits_from_centres(points, km.cluster_centers_, scale, length)
    share = np.ones(len(ids), np.int64)
    extra = B - len(ids)
    if extra > 0:
        want = counts / counts.sum() * B
        for _ in range(extra):
            share[int(np.argmax(want - share))] += 1
    logits = np.zeros((points.shape[0], int(share.sum())), np.float32)
    col = 0
    for i, k in enumerate(ids):
        sel = labels == k
        n = int(min(share[i], sel.sum()))
        km = KMeans(n_clusters=n, n_init=3, random_state=seed).fit(points[sel])
        d = np.linalg.norm(points[sel][:, None] - km.cluster_centers_[None], axis=-1)
        logits[np.ix_(np.flatnonzero(sel), np.arange(col, col + n))] = scale * (1 + np.exp(-d / max(length, 1e-9)))
        col += n
    return logits[:, :col]


def occlusion_contacts(data: TrainData, f: int) -> int:
    """Pixels where two different objects' masks touch (4-neighbours) in frame f: a proxy for occlusion."""
    if data.instance_mask is None:
        return 0
    lab = data.instance_mask[f]
    off = data.content_offset
    base = np.where((lab > off) & (off > 0), lab - off, lab)
    n = 0
    for a, b in ((base[1:], base[:-1]), (base[:, 1:], base[:, :-1])):
        n += int(((a > 0) & (b > 0) & (a != b)).sum())
    return n


def rank_canonical_frames(data: TrainData) -> np.ndarray:
    """Without tracks: a frame of the middle half of the sequence where every instance is seen, none
    touches the image border, and the objects overlap little. Score = fg area / (1 + contacts /
    (sqrt(area) / 2)), contacts = pixels where two objects' masks meet (see occlusion_contacts); a
    carve from an occluded view mislabels the points behind the occluder."""
    t = data.tidx
    lo, hi = np.quantile(t, 0.25), np.quantile(t, 0.75)
    cands = np.flatnonzero((t >= lo) & (t <= hi))
    area = np.array([(data.fg_masks[f] > 0.5).sum() for f in cands], dtype=np.float64)
    border = np.array([bool((data.fg_masks[f][[0, -1]] > 0.5).any() or (data.fg_masks[f][:, [0, -1]] > 0.5).any())
                       for f in cands])
    if data.instance_mask is not None:
        ids = np.unique(data.instance_mask)
        ids = ids[ids != 0]
        complete = np.array([np.isin(ids, np.unique(data.instance_mask[f])).all() for f in cands])
    else:
        complete = np.ones(len(cands), bool)
    contacts = np.array([occlusion_contacts(data, f) for f in cands], dtype=np.float64)
    quality = area / (1.0 + contacts / np.maximum(np.sqrt(area) / 2, 1.0))
    score = quality * (~border) * complete
    if score.max() <= 0:
        score = quality * complete if (quality * complete).max() > 0 else area
    return cands[np.argsort(-score, kind="stable")]


def _carved(data: TrainData, cano: int, params: dict, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng([seed, 7, cano])
    pts, cols, labels = carve_points(data, cano, params, rng)
    if pts.shape[0] > params["num_fg_init"]:
        sel = np.sort(rng.choice(pts.shape[0], params["num_fg_init"], replace=False))
        pts, cols, labels = pts[sel], cols[sel], labels[sel]
    return pts, cols, labels


def _carve_and_fit(data: TrainData, cano: int, params: dict, seed: int, iters: int) -> float:
    """Residual (px, forward + coverage) of a short silhouette fit from canonical frame `cano`."""
    from .silhouette import fit_bases_to_silhouettes

    pts, _, labels = _carved(data, cano, params, seed)
    fg_extent = robust_extent(pts)
    logits = instance_aware_coefs(pts, labels, params["num_bases"], params["init_coef_scale"],
                                  params["init_coef_length"] * 2 * fg_extent, seed)
    B, T = logits.shape[1], data.num_timesteps
    rot = IDENTITY_6D.reshape(1, 1, 6).repeat(B, T, 1)
    tr = torch.zeros(B, T, 3)
    _, _, info = fit_bases_to_silhouettes(
        data, pts, logits, labels, rot, tr, cano, _scale_without_depth(data, pts, fg_extent), iters=max(iters, 1),
        max_points=params["silhouette_fit_points"], frames_per_iter=params["silhouette_fit_frames"],
        pool=params["silhouette_pixels"], seed=seed, w_still=params["silhouette_fit_still"],
        w_smooth=params["silhouette_fit_smooth"], gap_fill=params["gap_interpolation"])
    return float(info["silhouette_fit_forward_px"] + info["silhouette_fit_coverage_px"])


def _scale_without_depth(data: TrainData, pts: np.ndarray, fg_extent: float) -> float:
    # the objects move: their extent at one time says little; use the volume (or the camera distance)
    if data.point_cloud is not None and len(data.point_cloud) >= 8:
        lo, hi = _volume_box(data)
        scale = float(np.max(hi - lo) / 2)
    else:
        dist = np.linalg.norm(camera_centers(data.w2c) - pts.mean(0), axis=1)
        scale = float(0.25 * np.median(dist))
    return max(scale, fg_extent)


def _init_without_tracks(data: TrainData, params: dict, rng: np.random.Generator, seed: int) -> InitResult:
    T = data.num_timesteps
    if data.has_depth:
        # monocular with depth but no tracks: the canonical frame's fg pixels
        counts = [(data.fg_masks[f] > 0.5).sum() for f in range(data.num_frames)]
        cano = int(np.argmax(counts))
        m = (data.fg_masks[cano] > 0.5) & data.depth_valid[cano]
        rr, cc = np.nonzero(m)
        if rr.size == 0:
            raise MogafError("reconstruction init: no foreground pixel with valid depth")
        sel = np.sort(rng.choice(rr.size, min(params["num_fg_init"], rr.size), replace=False))
        uv = np.stack([cc[sel] + 0.5, rr[sel] + 0.5], axis=1)
        pts = unproject(uv, data.depth[cano][rr[sel], cc[sel]], data.K[cano], data.w2c[cano])
        cols = data.images[cano][rr[sel], cc[sel]]
        labels = pixel_labels(data, cano, rr[sel], cc[sel])
    else:
        if params["canonical_frame"] >= 0:
            cano = params["canonical_frame"]
        else:
            ranked = rank_canonical_frames(data)[: max(1, params["canonical_candidates"])]
            cano = int(ranked[0])
            if len(ranked) > 1 and params["silhouette_fit_iters"] > 0 and data.num_timesteps > 1:
                # the best-scored frame is not always the best start: keep the one whose short
                # silhouette fit leaves the smallest residual
                trials = []
                for c in ranked:
                    r = _carve_and_fit(data, int(c), params, seed, params["silhouette_fit_iters"] // 4)
                    trials.append(r)
                cano = int(ranked[int(np.argmin(trials))])
        pts, cols, labels = _carved(data, cano, params, seed)
    fg_extent = robust_extent(pts)
    logits = instance_aware_coefs(pts, labels, params["num_bases"], params["init_coef_scale"],
                                  params["init_coef_length"] * 2 * fg_extent, seed)
    B = logits.shape[1]
    fg = gaussian_tensors(pts, cols, rng, params["init_opacity"], params["sh_degree"], True, logits)
    fg["labels"] = torch.tensor(labels, dtype=torch.int64)
    rot = IDENTITY_6D.reshape(1, 1, 6).repeat(B, T, 1)
    tr = torch.zeros(B, T, 3)
    bg = None
    bg_pts = np.zeros((0, 3))
    if _use_bg(params, data):
        if data.has_depth:
            bg_pts, bg_cols = _bg_from_depth(data, params["num_bg_init"], rng)
        else:
            bg_pts, bg_cols = _bg_outside_masks(data, params["num_bg_init"], rng)
        if bg_pts.shape[0] >= 4:
            bg = gaussian_tensors(bg_pts, bg_cols, rng, params["init_opacity"], params["sh_degree"], False)
    if bg_pts.shape[0]:
        scene_scale = robust_extent(np.concatenate([pts, bg_pts]))
    elif data.has_depth:
        scene_scale = fg_extent
    else:
        scene_scale = _scale_without_depth(data, pts, fg_extent)
    info = {"canonical_frame": cano, "fg_extent": fg_extent, "num_clusters": B}
    source = "identity"
    if params["silhouette_fit_iters"] > 0 and data.num_timesteps > 1:
        from .silhouette import fit_bases_to_silhouettes

        rot, tr, sinfo = fit_bases_to_silhouettes(
            data, pts, logits, labels, rot, tr, cano, scene_scale, iters=params["silhouette_fit_iters"],
            max_points=params["silhouette_fit_points"], frames_per_iter=params["silhouette_fit_frames"],
            pool=params["silhouette_pixels"], seed=seed, w_still=params["silhouette_fit_still"],
            w_smooth=params["silhouette_fit_smooth"], gap_fill=params["gap_interpolation"])
        info.update(sinfo)
        source = "silhouette"
        if params["hull_min_fraction"] > 0:
            from .silhouette import carve_with_motion

            keep = carve_with_motion(data, pts, logits, rot, tr, dilate=params["carve_dilate"],
                                     min_fraction=params["hull_min_fraction"])
            info["hull_kept_fraction"] = float(keep.mean())
            if keep.sum() >= 32:
                pts, cols, labels, logits = pts[keep], cols[keep], labels[keep], logits[keep]
                # refill the budget with jittered copies of the survivors
                n_more = params["num_fg_init"] - pts.shape[0]
                if n_more > 0:
                    src = rng.integers(0, pts.shape[0], size=n_more)
                    jitter = rng.normal(size=(n_more, 3)) * knn_scale(pts, 3)[src, None] * 0.5
                    pts = np.concatenate([pts, pts[src] + jitter])
                    cols, labels, logits = (np.concatenate([cols, cols[src]]), np.concatenate([labels, labels[src]]),
                                            np.concatenate([logits, logits[src]]))
                fg = gaussian_tensors(pts, cols, rng, params["init_opacity"], params["sh_degree"], True, logits)
                fg["labels"] = torch.tensor(labels, dtype=torch.int64)
    return InitResult(fg, rot, tr, bg, scene_scale, cano, source, info)


def _bg_outside_masks(data: TrainData, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Volume points never inside a (dilated) fg mask of a frame that sees them."""
    lo, hi = _volume_box(data)
    cand = lo + rng.random((max(4 * n, 1000), 3)) * (hi - lo)
    ok = np.ones(cand.shape[0], bool)
    seen = np.zeros(cand.shape[0])
    col = np.zeros((cand.shape[0], 3))
    step = max(1, data.num_frames // 32)
    for f in range(0, data.num_frames, step):
        m = _dilate(data.fg_masks[f] > 0.5, 2)
        uv, z = project(cand, data.K[f], data.w2c[f])
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < data.width) & (uv[:, 1] < data.height)
        uvs = np.where(inside[:, None], uv, 0.0)
        ok &= ~(inside & sample_pixels(m, uvs))
        seen += inside
        col += inside[:, None] * sample_pixels(data.images[f], uvs)
    keep = ok & (seen > 0)
    P, C = cand[keep], col[keep] / np.maximum(seen[keep, None], 1)
    if P.shape[0] > n:
        sel = np.sort(rng.choice(P.shape[0], n, replace=False))
        P, C = P[sel], C[sel]
    return P, C


def initialise(data: TrainData, params: dict, seed: int) -> InitResult:
    rng = np.random.default_rng(seed)
    if data.has_tracks and data.has_depth:
        return _init_from_tracks(data, params, rng, seed)
    return _init_without_tracks(data, params, rng, seed)
