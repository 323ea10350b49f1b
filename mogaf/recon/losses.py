"""Losses of the reconstruction stage (after Shape-of-Motion's trainer).

Written from the definitions: robust masked L1 with a quantile cut-off
(large residuals ignored), SSIM with an 11x11 Gaussian window (sigma 1.5,
valid convolution, as pytorch_msssim; cut to the image's shorter side, odd,
for images smaller than the window, e.g. a coarse level of a tiny scene), image-gradient matching of disparity,
second differences (acceleration) for smoothness.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F


def _gauss_window(size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float32) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


_WINDOW = _gauss_window()


def ssim(img0: torch.Tensor, img1: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of two (B, H, W, C) images in [0, 1] (differentiable)."""
    x = img0.permute(0, 3, 1, 2)
    y = img1.permute(0, 3, 1, 2)
    C = x.shape[1]
    w = _WINDOW.to(device=x.device, dtype=x.dtype)
    side = min(x.shape[2], x.shape[3])
    if side < w.numel():
        w = _gauss_window(side - (1 - side % 2)).to(device=x.device, dtype=x.dtype)
    wx = w.reshape(1, 1, 1, -1).expand(C, 1, 1, -1)
    wy = w.reshape(1, 1, -1, 1).expand(C, 1, -1, 1)

    def blur(z: torch.Tensor) -> torch.Tensor:
        return F.conv2d(F.conv2d(z, wx, groups=C), wy, groups=C)

    c1, c2 = 0.01**2, 0.03**2
    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    cs = (2 * sxy + c2) / (sxx + syy + c2)
    s = ((2 * mx * my + c1) / (mx * mx + my * my + c1)) * cs
    return s.mean()


def rgb_loss(pred: torch.Tensor, gt: torch.Tensor, ssim_weight: float = 0.2) -> torch.Tensor:
    """(1 - w) L1 + w (1 - SSIM) on (B, H, W, 3)."""
    l1 = (pred - gt).abs().mean()
    if ssim_weight <= 0:
        return l1
    return (1 - ssim_weight) * l1 + ssim_weight * (1 - ssim(pred, gt))


def linear_quantile(flat: torch.Tensor, q: float) -> torch.Tensor:
    """torch.quantile(flat, q) (linear interpolation) bit for bit, from two
    order statistics (kthvalue) instead of a full sort: ~8x faster on a
    160x120 image. Same rank and weight arithmetic, in the input's dtype; a
    NaN anywhere gives NaN, as torch.quantile does."""
    n = flat.numel()
    if n == 0 or bool(torch.isnan(flat).any()):
        return torch.quantile(flat, q)
    rank = torch.tensor(q, dtype=flat.dtype, device=flat.device) * (n - 1)
    below = int(rank.to(torch.int64))
    above = int(rank.ceil().to(torch.int64))
    low = torch.kthvalue(flat, below + 1).values
    high = torch.kthvalue(flat, above + 1).values if above != below else low
    return torch.lerp(low, high, rank - below)


def masked_l1(
    pred: torch.Tensor, gt: torch.Tensor, weight: torch.Tensor | None = None, quantile: float = 1.0
) -> torch.Tensor:
    """Weighted mean of |pred - gt| (averaged over the last axis), ignoring residuals above `quantile`.

    pred, gt: (..., D); weight broadcastable to (..., 1).
    """
    res = (pred - gt).abs().mean(dim=-1, keepdim=True)
    if weight is None:
        weight = torch.ones_like(res)
    weight = weight.expand_as(res)
    if res.numel() == 0:
        return pred.sum() * 0.0
    if quantile < 1.0:
        sel = weight > 0
        if sel.any():
            flat = res.detach()[sel]
            if flat.numel() > 1 << 24:  # torch.quantile limit
                flat = flat[:: flat.numel() // (1 << 24) + 1]
            cut = linear_quantile(flat, quantile)
            weight = weight * (res.detach() <= cut).to(weight.dtype)
    return (res * weight).sum() / weight.sum().clamp_min(1e-8)


def gradient_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor, quantile: float = 0.95) -> torch.Tensor:
    """L1 between finite differences of (B, H, W, 1) maps where both pixels are in `mask`."""
    mx = mask[:, :, 1:] * mask[:, :, :-1]
    my = mask[:, 1:, :] * mask[:, :-1, :]
    gx_p, gx_g = pred[:, :, 1:] - pred[:, :, :-1], gt[:, :, 1:] - gt[:, :, :-1]
    gy_p, gy_g = pred[:, 1:, :] - pred[:, :-1, :], gt[:, 1:, :] - gt[:, :-1, :]
    return masked_l1(gx_p, gx_g, mx, quantile) + masked_l1(gy_p, gy_g, my, quantile)


def accel_loss(x: torch.Tensor, dim: int = 1) -> torch.Tensor:
    """Mean norm of second differences along `dim` (last axis = vector)."""
    n = x.shape[dim]
    if n < 3:
        return x.sum() * 0.0
    a = 2 * x.narrow(dim, 1, n - 2) - x.narrow(dim, 0, n - 2) - x.narrow(dim, 2, n - 2)
    return a.norm(dim=-1).mean()


def jerk_loss(x: torch.Tensor, dim: int = 1) -> torch.Tensor:
    """Mean norm of third differences along `dim` (last axis = vector): zero
    for motion at constant acceleration, which accel_loss slows down."""
    n = x.shape[dim]
    if n < 4:
        return x.sum() * 0.0
    j = x.narrow(dim, 3, n - 3) - 3 * x.narrow(dim, 2, n - 3) + 3 * x.narrow(dim, 1, n - 3) - x.narrow(dim, 0, n - 3)
    return j.norm(dim=-1).mean()


# recon.smooth_bases: the finite difference of the bases over time that the smoothness prior penalises
SMOOTHNESS_PRIORS = {"acceleration": accel_loss, "jerk": jerk_loss}


def basis_smoothness(
    rot6d: torch.Tensor, transl: torch.Tensor, scale: float = 1.0, prior: str = "acceleration"
) -> torch.Tensor:
    """SoM: accel(rot) + 2 accel(translation) of the bases over time
    (translation / scene scale); prior "jerk": the same with third differences."""
    difference = SMOOTHNESS_PRIORS[prior]
    return difference(rot6d) + 2.0 * difference(transl / scale)


def z_velocity_loss(means_nb: torch.Tensor, cam_centers: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
    """SoM z-acceleration term: squared motion along the viewing ray.

    means_nb: (N, 3, K, 3) positions at t-1, t, t+1 for K frames;
    cam_centers: (K, 3).
    """
    ray = means_nb[:, 1] - cam_centers[None]
    ray = ray / ray.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    v0 = ((means_nb[:, 1] - means_nb[:, 0]) * ray).sum(-1) / scale
    v1 = ((means_nb[:, 2] - means_nb[:, 1]) * ray).sum(-1) / scale
    return (v0**2).mean() + (v1**2).mean()


def nearest_neighbours(points: torch.Tensor, k: int) -> torch.Tensor:
    """(N, k') int64 indices of each point's k nearest other points (k' = min(k, N - 1)), by a k-d tree.

    The tree's k' + 1 nearest hits with the point itself left out: among exact duplicates (a densification
    clone and its source) the twin may come before it, so it is removed wherever it stands (and, among more
    than k' + 1 duplicates, where it is not among them, the farthest hit goes)."""
    from scipy.spatial import cKDTree

    pts = points.detach().cpu().double().numpy()
    kk = min(int(k), pts.shape[0] - 1)
    if kk < 1:
        return torch.zeros((pts.shape[0], 0), dtype=torch.int64)
    _, idx = cKDTree(pts).query(pts, k=kk + 1)
    itself = idx == np.arange(pts.shape[0])[:, None]
    # a stable sort moves the point itself (or, where absent, nothing) to the end, keeping the others' order
    others = np.take_along_axis(idx, np.argsort(itself, axis=1, kind="stable"), axis=1)[:, :kk]
    return torch.from_numpy(others.astype(np.int64))


def pair_distances(x: torch.Tensor, nbrs: torch.Tensor, eps: float) -> torch.Tensor:
    """(N, k) distances from each point of x (N, 3) to its neighbours nbrs (N, k); eps keeps the gradient finite
    where two points coincide (a densification clone)."""
    d = x[:, None, :] - x[nbrs]
    return (d.square().sum(-1) + eps * eps).sqrt()


class _LastDimVariance(torch.autograd.Function):
    """Welford's recurrence over the last dimension, in float64 as ATen's CPU
    kernel accumulates, rounded to the input's dtype; the backward is ATen's
    var_backward written out. Same bits as torch.var forward and backward."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(x)
        xd = x.double()
        mean = xd[..., 0]
        m2 = torch.zeros_like(mean)
        for k in range(1, x.shape[-1]):
            delta = xd[..., k] - mean
            mean = mean + delta / (k + 1)
            m2 = m2 + delta * (xd[..., k] - mean)
        return (m2 / (x.shape[-1] - 1)).to(x.dtype)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        (x,) = ctx.saved_tensors
        return (2.0 / (x.shape[-1] - 1)) * grad.unsqueeze(-1) * (x - x.mean(-1, keepdim=True))


def last_dim_variance(x: torch.Tensor) -> torch.Tensor:
    """torch.var(x, dim=-1) (unbiased) of a float32 CPU tensor with a short
    last dimension (a Gaussian's three log-scales), bit for bit, forward and
    backward: ATen's reduction over a dimension this short took milliseconds
    per step. Other tensors go to torch.var itself."""
    if x.device.type != "cpu" or x.dtype != torch.float32 or not 2 <= x.shape[-1] <= 8:
        return torch.var(x, dim=-1)
    return _LastDimVariance.apply(x)
