"""Pure-torch fallback compositor: packed (Gaussian, pixel) pairs, analytic backward.

Used when the C++ kernel cannot be built (no compiler) or when forced with
backend="torch" / MOGAF_RENDER_BACKEND=torch. Same semantics as the kernel and
the dense reference (see csrc/rasterize.cpp), memory O(number of covered pixels).

Forward: enumerate, per Gaussian and per row of its radius box, only the pixels
inside its alpha >= 1/255 ellipse (a conservative row span), evaluate alpha,
drop alpha < 1/255, sort the pairs by (pixel, depth rank), get the transmittance
by a segmented cumulative sum of log(1 - alpha) in float64, apply the early stop
(T <= 1e-4) and accumulate with index_add. Backward: the closed-form 3DGS
gradients over the kept pairs (suffix sums per pixel by a global float64 cumsum),
one index_add into the per-Gaussian gradients; no autograd through sort/cumsum.
"""

from __future__ import annotations

import math

import torch
from torch.autograd.function import once_differentiable

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
LOG_T_MIN = math.log(1e-4)


def box_range(m: torch.Tensor, r: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Inclusive pixel range with centre inside |m - (i + 0.5)| <= r, clipped to [0, n)."""
    md, rd = m.double(), r.double()
    lo = torch.ceil(md - rd - 0.5).clamp(-4, n + 4).long()
    hi = torch.floor(md + rd - 0.5).clamp(-4, n + 4).long()

    def inside(i: torch.Tensor) -> torch.Tensor:
        return (m - (i.to(m.dtype) + 0.5)).abs() <= r

    lo = torch.where(inside(lo - 1), lo - 1, torch.where(inside(lo), lo, lo + 1))
    hi = torch.where(inside(hi + 1), hi + 1, torch.where(inside(hi), hi, hi - 1))
    return lo.clamp(min=0), hi.clamp(max=n - 1)


def _segment_ids(counts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """For segment lengths `counts`, return (segment id, index within segment) of every element."""
    total = int(counts.sum())
    seg = torch.repeat_interleave(torch.arange(counts.numel()), counts, output_size=total)
    starts = torch.cumsum(counts, 0) - counts
    local = torch.arange(total) - starts.index_select(0, seg)
    return seg, local


def enumerate_pairs(mx, my, a, b, c, o, rx, ry, width, height):
    """Candidate (Gaussian, pixel) pairs: per box row, the conservative ellipse span.

    Inputs are 1D per-Gaussian tensors (detached). Returns (g, i, j) int64
    tensors, grouped by Gaussian in index order and row-major within a Gaussian.
    """
    i0, i1 = box_range(mx, rx, width)
    j0, j1 = box_range(my, ry, height)
    ok = (o.double() * 255.0 >= 1.0) & ((rx > 0) | (ry > 0))
    nrow = torch.where(ok & (i1 >= i0), (j1 - j0 + 1).clamp(min=0), torch.zeros_like(j0))
    rg, rlocal = _segment_ids(nrow)
    j = j0.index_select(0, rg) + rlocal

    def per_row(t):
        return t.double().index_select(0, rg)

    # Row span of the relaxed ellipse sigma <= tau, tau = ln(255 o) (as the kernel).
    ad, bd, cd = a.double(), b.double(), c.double()
    det = ad * cd - bd * bd
    tau = torch.log(255.0 * o.double().clamp(min=ALPHA_MIN)) * (1.0 + 1e-4) + 1e-3
    regular = (det > 0) & (ad > 0)
    inv_a = torch.where(ad > 0, 1.0 / torch.where(ad > 0, ad, torch.ones_like(ad)), torch.zeros_like(ad))
    dy = per_row(my) - (j.double() + 0.5)
    disc = per_row(2.0 * ad * tau) - per_row(det) * dy * dy
    hw = torch.sqrt(disc.clamp(min=0)) * per_row(inv_a)
    ctr = per_row(mx) + per_row(bd * inv_a) * dy - 0.5
    lo = torch.ceil(ctr - hw).clamp(-4, width + 4).long()
    hi = torch.floor(ctr + hw).clamp(-4, width + 4).long()
    reg = regular.index_select(0, rg)
    i0r, i1r = i0.index_select(0, rg), i1.index_select(0, rg)
    ia = torch.where(reg, torch.maximum(i0r, lo), i0r)
    ib = torch.where(reg, torch.minimum(i1r, hi), i1r)
    npix = torch.where(~reg | (disc >= 0), (ib - ia + 1).clamp(min=0), torch.zeros_like(ia))
    row, plocal = _segment_ids(npix)
    return rg.index_select(0, row), ia.index_select(0, row) + plocal, j.index_select(0, row)


class _TorchRaster(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, radii, depths, width, height):
        dtype = means2d.dtype
        M, NC = feats.shape
        HW = width * height
        # Depth-rank space: Gaussian r is the r-th from the front; pairs come out in rank order.
        order = torch.argsort(depths.detach(), stable=True)
        cols = [t.index_select(0, order) for t in (*means2d.unbind(1), *conics.unbind(1), opacities)]
        mx, my, a, b, c, o = cols
        rad = radii.index_select(0, order).to(dtype)
        g, i, j = enumerate_pairs(mx, my, a, b, c, o, rad[:, 0], rad[:, 1], width, height)
        dx = mx.index_select(0, g) - (i.to(dtype) + 0.5)
        dy = my.index_select(0, g) - (j.to(dtype) + 0.5)
        sigma = 0.5 * (a.index_select(0, g) * dx * dx + c.index_select(0, g) * dy * dy)
        sigma += b.index_select(0, g) * dx * dy
        G = torch.exp(-sigma)
        raw = o.index_select(0, g) * G
        alpha = torch.clamp(raw, max=ALPHA_MAX)
        sel = (alpha >= ALPHA_MIN).nonzero().squeeze(1)
        # Pixel-major order; the stable sort keeps depth order within a pixel.
        pix = (j * width + i).index_select(0, sel).to(torch.int32)
        pix, perm = torch.sort(pix, stable=True)
        sel = sel.index_select(0, perm)
        alpha = alpha.index_select(0, sel)
        counts = torch.bincount(pix, minlength=HW)
        starts = torch.cumsum(counts, 0) - counts
        pix = pix.long()
        log1m = torch.log1p(-alpha.double())
        cs = torch.cumsum(log1m, 0)
        cs_excl = cs - log1m
        base = cs_excl.index_select(0, starts.index_select(0, pix))
        keep = ((cs - base) > LOG_T_MIN).nonzero().squeeze(1)
        # Compact to the composited pairs.
        sel, pix, alpha = sel.index_select(0, keep), pix.index_select(0, keep), alpha.index_select(0, keep)
        g = g.index_select(0, sel)
        T = torch.exp((cs_excl - base).index_select(0, keep)).to(dtype)
        w = alpha * T
        rank_f = feats.index_select(0, order)
        acc = torch.zeros(HW, NC, dtype=dtype)
        acc.index_add_(0, pix, w[:, None] * rank_f.index_select(0, g))
        log_tf = torch.zeros(HW, dtype=torch.float64)
        log_tf.index_add_(0, pix, log1m.index_select(0, keep))
        Tf = torch.exp(log_tf).to(dtype)
        ctx.save_for_backward(
            a, b, c, rank_f, order, g, pix, dx.index_select(0, sel), dy.index_select(0, sel),
            G.index_select(0, sel), raw.index_select(0, sel), alpha, T, Tf,
        )  # fmt: skip
        ctx.dims = (width, height)
        return acc.reshape(height, width, NC), (1 - Tf).reshape(height, width, 1)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_acc, g_alpha):
        a, b, c, rank_f, order, g, pix, dx, dy, G, raw, alpha, T, Tf = ctx.saved_tensors
        width, height = ctx.dims
        dtype = rank_f.dtype
        M, NC = rank_f.shape
        HW = width * height
        gC = g_acc.reshape(HW, NC).to(dtype).index_select(0, pix)
        w = alpha * T
        dot = (gC * rank_f.index_select(0, g)).sum(1)
        cs = torch.cumsum((w * dot).double(), 0)
        counts = torch.bincount(pix, minlength=HW)
        ends = torch.cumsum(counts, 0) - 1
        suffix = (cs.index_select(0, ends.index_select(0, pix)) - cs).to(dtype)
        gATf = (g_alpha.reshape(HW).to(dtype) * Tf).index_select(0, pix)
        dLda = T * dot - (suffix - gATf) / (1 - alpha)
        dLda = torch.where(raw < ALPHA_MAX, dLda, torch.zeros_like(dLda))
        dLds = -alpha * dLda
        ag, bg, cg = a.index_select(0, g), b.index_select(0, g), c.index_select(0, g)
        rec = torch.empty(g.numel(), 6 + NC, dtype=dtype)
        rec[:, 0] = (ag * dx + bg * dy) * dLds
        rec[:, 1] = (bg * dx + cg * dy) * dLds
        rec[:, 2] = 0.5 * dx * dx * dLds
        rec[:, 3] = dx * dy * dLds
        rec[:, 4] = 0.5 * dy * dy * dLds
        rec[:, 5] = G * dLda
        torch.mul(gC, w[:, None], out=rec[:, 6:])
        out = torch.zeros(M, 6 + NC, dtype=dtype)
        out.index_add_(0, g, rec)
        grads = torch.empty_like(out)
        grads.index_copy_(0, order, out)
        return (
            grads[:, 0:2].contiguous(),
            grads[:, 2:5].contiguous(),
            grads[:, 5].contiguous(),
            grads[:, 6:].contiguous(),
            None,
            None,
            None,
            None,
        )


def composite_torch(means2d, conics, opacities, feats, radii, depths, width, height):
    """(acc (H, W, NC), alpha (H, W, 1)) with the packed-pairs torch compositor."""
    return _TorchRaster.apply(means2d, conics, opacities, feats, radii, depths, width, height)
