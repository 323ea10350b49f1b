"""Slow dense reference compositor: every Gaussian against every pixel.

Plain torch autograd end to end (no custom backward), so it checks both the
forward and the analytic backward passes of the fast backends. Memory is
O(M x H x W): use it on small scenes (tests) only.

It implements exactly the semantics documented in csrc/rasterize.cpp:
pixel centre inside the closed radius box, alpha = min(0.99, o e^-sigma)
>= 1/255, front-to-back by depth (ties by index), and a pixel stops at the first
Gaussian that would bring its transmittance to <= 1e-4 (not composited).
"""

from __future__ import annotations

import torch

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4


def composite_dense(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    feats: torch.Tensor,
    radii: torch.Tensor,
    depths: torch.Tensor,
    width: int,
    height: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite M projected Gaussians; returns (acc (H, W, NC), alpha (H, W, 1)).

    Gaussians are composited front to back by `depths` (stable); `acc` is the
    un-normalised sum of w_i f_i, alpha = 1 - prod(1 - alpha_i).
    """
    dtype = means2d.dtype
    M, NC = feats.shape
    P = width * height
    if M == 0:
        acc = feats.sum() * 0 + torch.zeros(height, width, NC, dtype=dtype)
        return acc, torch.zeros(height, width, 1, dtype=dtype) + means2d.sum() * 0
    order = torch.argsort(depths.detach(), stable=True)
    m = means2d[order]
    con = conics[order]
    o = opacities[order]
    f = feats[order]
    r = radii[order].to(dtype)
    px = (torch.arange(width, dtype=dtype) + 0.5).repeat(height)
    py = (torch.arange(height, dtype=dtype) + 0.5).repeat_interleave(width)
    dx = m[:, 0:1] - px[None, :]
    dy = m[:, 1:2] - py[None, :]
    a, b, c = con[:, 0:1], con[:, 1:2], con[:, 2:3]
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    raw = o[:, None] * torch.exp(-sigma)
    alpha = torch.clamp(raw, max=ALPHA_MAX)
    valid = (alpha >= ALPHA_MIN) & (dx.abs() <= r[:, 0:1]) & (dy.abs() <= r[:, 1:2])
    ones = torch.ones_like(alpha)
    t_incl = torch.cumprod(torch.where(valid, 1 - alpha, ones), 0)
    keep = valid & (t_incl > T_MIN)
    a_k = torch.where(keep, alpha, torch.zeros_like(alpha))
    cp = torch.cumprod(1 - a_k, 0)
    t_excl = torch.cat([torch.ones(1, P, dtype=dtype), cp[:-1]], 0)
    w = a_k * t_excl
    acc = (w.T @ f).reshape(height, width, NC)
    alpha_img = (1 - cp[-1]).reshape(height, width, 1)
    return acc, alpha_img
