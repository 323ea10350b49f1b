"""Silhouette terms: a long-range 2D signal for motion without depth or tracks.

Not part of Shape-of-Motion (which starts its bases from 3D tracks). For
multi-view-without-depth scenes (D-NeRF layout) the bases start at the
identity and the photometric loss only sees an object where the rendering
already overlaps it. Two chamfer-like terms between the projected
Gaussian centres and the observed masks give gradients from any distance:

  forward  = mean over centres of the distance (px) to the nearest fg pixel
             (distance transform of the union of all fg masks, so a centre
             hidden behind another object is not penalised), weighted by
             opacity;
  coverage = per instance k, mean over sampled pixels of instance k of the
             distance to the nearest centre labelled k (the instance the
             Gaussian was initialised on): each object's points must span
             its own silhouette.

Both are divided by max(H, W). `fit_bases_to_silhouettes` uses them (plus
basis smoothness) to fit the motion bases to every observed frame before
the photometric optimisation, growing the time window from the canonical
frame outwards (full batch, no rendering: cheap).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ..optim import Adam
from ..representation import blend_bases
from .data import TrainData
from .interpolation import gap_interpolation
from .losses import basis_smoothness


class SilhouetteTargets:
    def __init__(self, data: TrainData, pool: int, gen: torch.Generator, device: torch.device | str = "cpu"):
        import cv2

        self.H, self.W = data.height, data.width
        self.norm = float(max(self.H, self.W))
        dts = []
        for f in range(data.num_frames):
            bgm = (data.fg_masks[f] <= 0.5).astype(np.uint8)
            if bgm.min() == 0:
                dts.append(cv2.distanceTransform(bgm, cv2.DIST_L2, 5))
            else:  # no fg in this frame: a constant, gradient-free map
                dts.append(np.zeros(bgm.shape, np.float32))
        self.dt = torch.tensor(np.stack(dts), dtype=torch.float32, device=device)[:, None]  # (F,1,H,W)
        lab = data.instance_mask if data.instance_mask is not None else (data.fg_masks > 0.5).astype(np.int64)
        self.ids = [int(k) for k in np.unique(lab) if k != 0]
        F_ = data.num_frames
        # a fixed pool of `pool` pixels (with replacement) per frame and instance
        self.pixels = torch.zeros((len(self.ids), F_, pool, 2), dtype=torch.float32)
        self.present = torch.zeros((len(self.ids), F_), dtype=torch.bool)
        for i, k in enumerate(self.ids):
            for f in range(F_):
                rr, cc = np.nonzero(lab[f] == k)
                if rr.size == 0:
                    continue
                idx = torch.randint(0, rr.size, (pool,), generator=gen).numpy()
                self.pixels[i, f, :, 0] = torch.tensor(cc[idx] + 0.5, dtype=torch.float32)
                self.pixels[i, f, :, 1] = torch.tensor(rr[idx] + 0.5, dtype=torch.float32)
                self.present[i, f] = True
        self.pixels = self.pixels.to(device)
        self.present = self.present.to(device)

    def terms(
        self,
        frames: torch.Tensor,
        uv: torch.Tensor,
        front: torch.Tensor,
        weight: torch.Tensor,
        labels: torch.Tensor | None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """uv (Fb, N, 2) projected centres in frames (Fb,), front (Fb, N) bool, weight (N,) -> (forward, coverage)."""
        Fb, N = uv.shape[:2]
        grid = torch.stack([uv[..., 0] / self.W * 2 - 1, uv[..., 1] / self.H * 2 - 1], -1)[:, None]  # (Fb,1,N,2)
        dt = F.grid_sample(self.dt[frames], grid, mode="bilinear", padding_mode="border", align_corners=False)[:, 0, 0]
        outside = F.relu(-uv[..., 0]) + F.relu(uv[..., 0] - self.W) + F.relu(-uv[..., 1]) + F.relu(uv[..., 1] - self.H)
        w = weight[None] * front.float()
        fwd = ((dt + outside) * w).sum() / w.sum().clamp_min(1e-6) / self.norm
        cov = uv.sum() * 0.0
        n = 0
        big = torch.tensor(1e6, dtype=uv.dtype, device=uv.device)
        for i, k in enumerate(self.ids):
            pres = self.present[i, frames]
            if not bool(pres.any()):
                continue
            sel = (labels == k) if labels is not None else torch.ones(N, dtype=torch.bool, device=uv.device)
            sel = sel & (weight > 0.05)
            if not bool(sel.any()):
                continue
            pts = uv[:, sel]  # (Fb, n_k, 2)
            d = torch.cdist(self.pixels[i, frames], pts)  # (Fb, M, n_k)
            d = torch.where(front[:, sel][:, None, :], d, big)
            dmin = d.min(dim=2).values  # (Fb, M)
            ok = pres & (front[:, sel].any(dim=1))
            if bool(ok.any()):
                cov = cov + dmin[ok].mean() / self.norm
                n += 1
        if n:
            cov = cov / n
        return fwd, cov


def project_batch(
    points: torch.Tensor, K: torch.Tensor, w2c: torch.Tensor, near: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """points (N, Fb, 3) world, K (Fb,3,3), w2c (Fb,4,4) -> uv (Fb, N, 2), front (Fb, N)."""
    cam = torch.einsum("fij,nfj->fni", w2c[:, :3, :3], points) + w2c[:, None, :3, 3]
    z = cam[..., 2]
    uvw = torch.einsum("fij,fnj->fni", K, cam)
    uv = uvw[..., :2] / z.clamp_min(near)[..., None]
    return uv, z > near


def fit_bases_to_silhouettes(
    data: TrainData,
    means: np.ndarray,
    coef_logits: np.ndarray,
    labels: np.ndarray,
    rot: torch.Tensor,
    tr: torch.Tensor,
    cano: int,
    scale: float,
    *,
    iters: int,
    max_points: int,
    frames_per_iter: int,
    pool: int,
    seed: int,
    w_still: float = 0.0,
    w_smooth: float = 0.05,
    gap_fill: bool = True,
    smoothness: str = "acceleration",
) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """Fit the motion bases (and coefficients) so projected centres follow the masks of every frame."""
    if iters <= 0:
        return rot, tr, {}
    gen = torch.Generator().manual_seed(seed + 17)
    targets = SilhouetteTargets(data, pool, gen)
    N = means.shape[0]
    # One rigid basis per instance during the fit (sub-bases of an instance would otherwise tear it
    # apart: coverage only asks that *some* centre be near each pixel); afterwards every basis takes
    # the fitted motion of the instance its points belong to.
    inst_ids = np.unique(labels)
    owner = np.argmax(coef_logits, axis=1)
    basis_inst = np.zeros(coef_logits.shape[1], np.int64)
    for b in range(coef_logits.shape[1]):
        lb = labels[owner == b]
        basis_inst[b] = np.searchsorted(inst_ids, np.bincount(lb).argmax()) if lb.size else 0
    if max_points < N:
        pick = torch.randperm(N, generator=gen)[:max_points].sort().values.numpy()
    else:
        pick = np.arange(N)
    m = torch.tensor(means[pick], dtype=torch.float32)
    lab = torch.tensor(labels[pick], dtype=torch.int64)
    coefs = torch.nn.functional.one_hot(torch.tensor(np.searchsorted(inst_ids, labels[pick])), len(inst_ids)).float()
    r = rot[:1].detach().clone().float().repeat(len(inst_ids), 1, 1).requires_grad_(True)
    t = tr[:1].detach().clone().float().repeat(len(inst_ids), 1, 1).requires_grad_(True)
    K = torch.tensor(data.K, dtype=torch.float32)
    w2c = torch.tensor(data.w2c, dtype=torch.float32)
    tidx = torch.tensor(data.tidx, dtype=torch.int64)
    T = data.num_timesteps
    c0 = int(tidx[cano])
    opt = Adam([{"params": [r], "lr": 1e-2}, {"params": [t], "lr": 1e-2 * scale}])
    ones = torch.ones(m.shape[0])
    grow = max(1, int(0.7 * iters))
    hist = []
    gi = gap_interpolation(T, data.tidx) if gap_fill else None
    knots = torch.tensor(np.unique(data.tidx))
    for i in range(iters):
        w = int(min(T, 2 + (T - 2) * i / grow))
        allowed = torch.nonzero((tidx - c0).abs() <= w, as_tuple=False).squeeze(1)
        if allowed.numel() > frames_per_iter:
            frames = allowed[torch.randperm(allowed.numel(), generator=gen)[:frames_per_iter]]
        else:
            frames = allowed
        lo, hi = max(0, c0 - w), min(T - 1, c0 + w)
        with torch.no_grad():  # steps outside the window follow the edge (constant)
            r.data[:, hi + 1 :] = r.data[:, hi : hi + 1]
            t.data[:, hi + 1 :] = t.data[:, hi : hi + 1]
            r.data[:, :lo] = r.data[:, lo : lo + 1]
            t.data[:, :lo] = t.data[:, lo : lo + 1]
        ts = tidx[frames]
        R, tt = blend_bases(coefs, r[:, ts], t[:, ts])  # (n, Fb, 3, 3)
        pos = torch.einsum("nfij,nj->nfi", R, m) + tt
        uv, front = project_batch(pos, K[frames], w2c[frames], 1e-3 * scale)
        fwd, cov = targets.terms(frames, uv, front, ones, lab)
        smooth = basis_smoothness(r[:, lo : hi + 1], t[:, lo : hi + 1], scale, smoothness) if hi - lo >= 2 else fwd * 0
        still = (
            (
                (r[:, lo + 1 : hi + 1] - r[:, lo:hi]).norm(dim=-1).mean()
                + ((t[:, lo + 1 : hi + 1] - t[:, lo:hi]) / scale).norm(dim=-1).mean()
            )
            if hi > lo
            else fwd * 0
        )
        loss = fwd + cov + w_smooth * smooth + w_still * still
        opt.zero_grad()
        loss.backward()
        opt.step()
        if gi is not None:
            with torch.no_grad():
                M = torch.tensor(gi[1], dtype=torch.float32)
                for x in (r, t):
                    x.data[:, torch.tensor(gi[0])] = torch.einsum("gk,bkd->bgd", M, x.data[:, knots])
        if i % 50 == 0 or i == iters - 1:
            hist.append((i, float(fwd.detach()), float(cov.detach())))
    idx = torch.tensor(basis_inst)
    r_out, t_out = r.detach()[idx].clone(), t.detach()[idx].clone()
    info = {
        "silhouette_fit_forward_px": hist[-1][1] * targets.norm,
        "silhouette_fit_coverage_px": hist[-1][2] * targets.norm,
    }
    return r_out, t_out, info


@torch.no_grad()
def carve_with_motion(
    data: TrainData,
    means: np.ndarray,
    coef_logits: np.ndarray,
    rot: torch.Tensor,
    tr: torch.Tensor,
    *,
    dilate: int,
    min_fraction: float,
    chunk: int = 2048,
) -> np.ndarray:
    """Share of frames (that see it) in which each posed point falls in the dilated fg mask -> keep mask (N,).

    A visual hull over all observed frames, once the bases follow the masks.
    """
    import cv2

    masks = []
    k = np.ones((2 * dilate + 1, 2 * dilate + 1), np.uint8)
    for f in range(data.num_frames):
        mk = (data.fg_masks[f] > 0.5).astype(np.uint8)
        masks.append(cv2.dilate(mk, k) > 0 if dilate > 0 else mk > 0)
    masks_t = torch.tensor(np.stack(masks))
    K = torch.tensor(data.K, dtype=torch.float32)
    w2c = torch.tensor(data.w2c, dtype=torch.float32)
    ts = torch.tensor(data.tidx, dtype=torch.int64)
    N = means.shape[0]
    frac = np.zeros(N)
    for s in range(0, N, chunk):
        m = torch.tensor(means[s : s + chunk], dtype=torch.float32)
        c = torch.softmax(torch.tensor(coef_logits[s : s + chunk], dtype=torch.float32), -1)
        R, t = blend_bases(c, rot[:, ts].float(), tr[:, ts].float())
        pos = torch.einsum("nfij,nj->nfi", R, m) + t
        uv, front = project_batch(pos, K, w2c, 1e-6)
        col = uv[..., 0].floor().long()
        row = uv[..., 1].floor().long()
        inside = front & (col >= 0) & (row >= 0) & (col < data.width) & (row < data.height)
        fidx = torch.arange(data.num_frames)[:, None].expand_as(col)
        hit = masks_t[fidx, row.clamp(0, data.height - 1), col.clamp(0, data.width - 1)] & inside
        frac[s : s + chunk] = (hit.sum(0).float() / inside.sum(0).clamp_min(1).float()).numpy()
    return frac >= min_fraction
