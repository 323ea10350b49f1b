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
    local = torch.arange(total) - starts[seg]
    return seg, local


def enumerate_pairs(means2d, conics, opacities, radii, width, height):
    """Candidate (Gaussian, pixel) pairs: per box row, the conservative ellipse span.

    Returns (g, i, j) int64 tensors, grouped by Gaussian in index order.
    """
    m = means2d.detach()
    con = conics.detach().double()
    o = opacities.detach().double()
    rad = radii.to(m.dtype)
    i0, i1 = box_range(m[:, 0], rad[:, 0], width)
    j0, j1 = box_range(m[:, 1], rad[:, 1], height)
    ok = (o * 255.0 >= 1.0) & (radii[:, 0] >= 0) & (radii[:, 1] >= 0)
    nrow = torch.where(ok & (i1 >= i0), (j1 - j0 + 1).clamp(min=0), torch.zeros_like(j0))
    rg, rlocal = _segment_ids(nrow)
    j = j0[rg] + rlocal
    # Row span of the relaxed ellipse sigma <= tau, tau = ln(255 o) (as the kernel).
    a, b, c = con[rg, 0], con[rg, 1], con[rg, 2]
    det = a * c - b * b
    tau = torch.log(255.0 * o[rg].clamp(min=ALPHA_MIN)) * (1.0 + 1e-4) + 1e-3
    dy = m[rg, 1].double() - (j.double() + 0.5)
    disc = 2.0 * a * tau - det * dy * dy
    sq = torch.sqrt(disc.clamp(min=0))
    bdy = b * dy
    a_s = torch.where(a > 0, a, torch.ones_like(a))
    mx = m[rg, 0].double()
    lo = torch.ceil(mx - (-bdy + sq) / a_s - 0.5).clamp(-4, width + 4).long()
    hi = torch.floor(mx - (-bdy - sq) / a_s - 0.5).clamp(-4, width + 4).long()
    regular = (det > 0) & (a > 0)
    ia = torch.where(regular, torch.maximum(i0[rg], lo), i0[rg])
    ib = torch.where(regular, torch.minimum(i1[rg], hi), i1[rg])
    npix = torch.where(~regular | (disc >= 0), (ib - ia + 1).clamp(min=0), torch.zeros_like(ia))
    row, plocal = _segment_ids(npix)
    return rg[row], ia[row] + plocal, j[row]


class _TorchRaster(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, radii, depths, width, height):
        dtype = means2d.dtype
        M, NC = feats.shape
        HW = width * height
        # Work in depth-rank space: pairs are generated in rank order.
        order = torch.argsort(depths.detach(), stable=True)
        rank_m = means2d[order]
        rank_c = conics[order]
        rank_o = opacities[order]
        rank_f = feats[order]
        g, i, j = enumerate_pairs(rank_m, rank_c, rank_o, radii[order], width, height)
        dx = rank_m[g, 0] - (i.to(dtype) + 0.5)
        dy = rank_m[g, 1] - (j.to(dtype) + 0.5)
        a, b, c = rank_c[g, 0], rank_c[g, 1], rank_c[g, 2]
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
        G = torch.exp(-sigma)
        raw = rank_o[g] * G
        alpha = torch.clamp(raw, max=ALPHA_MAX)
        valid = alpha >= ALPHA_MIN
        sel = valid.nonzero().squeeze(1)
        pix = (j * width + i)[sel]
        g = g[sel]
        # (pixel, depth rank) order; keys are unique.
        key = pix * max(M, 1) + g
        key, perm = torch.sort(key)
        sel = sel[perm]
        pix = key // max(M, 1)
        g = key - pix * max(M, 1)
        alpha = alpha[sel]
        counts = torch.bincount(pix, minlength=HW)
        starts = torch.cumsum(counts, 0) - counts
        log1m = torch.log1p(-alpha.double())
        cs = torch.cumsum(log1m, 0)
        cs_excl = cs - log1m
        base = cs_excl[starts[pix]]
        keep = (cs - base) > LOG_T_MIN
        kidx = keep.nonzero().squeeze(1)
        # Compact to the composited pairs.
        sel, pix, g, alpha = sel[kidx], pix[kidx], g[kidx], alpha[kidx]
        T = torch.exp(cs_excl[kidx] - base[kidx]).to(dtype)
        w = alpha * T
        acc = torch.zeros(HW, NC, dtype=dtype)
        acc.index_add_(0, pix, w[:, None] * rank_f[g])
        log_tf = torch.zeros(HW, dtype=torch.float64)
        log_tf.index_add_(0, pix, log1m[kidx])
        Tf = torch.exp(log_tf).to(dtype)
        ctx.save_for_backward(
            rank_m, rank_c, rank_o, rank_f, order, g, pix, dx[sel], dy[sel], G[sel], raw[sel], alpha, T, Tf
        )
        ctx.dims = (width, height)
        return acc.reshape(height, width, NC), (1 - Tf).reshape(height, width, 1)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_acc, g_alpha):
        rank_m, rank_c, rank_o, rank_f, order, g, pix, dx, dy, G, raw, alpha, T, Tf = ctx.saved_tensors
        width, height = ctx.dims
        dtype = rank_m.dtype
        M, NC = rank_f.shape
        HW = width * height
        gC = g_acc.reshape(HW, NC)[pix]
        f = rank_f[g]
        dot = (gC * f).sum(1)
        w = alpha * T
        v = (w * dot).double()
        cs = torch.cumsum(v, 0)
        counts = torch.bincount(pix, minlength=HW)
        ends = torch.cumsum(counts, 0) - 1
        suffix = (cs[ends[pix]] - cs).to(dtype)
        gATf = (g_alpha.reshape(HW) * Tf)[pix]
        om = 1 - alpha
        dLda = T * dot - (suffix - gATf) / om
        dLda = torch.where(raw < ALPHA_MAX, dLda, torch.zeros_like(dLda))
        dLds = -alpha * dLda
        a, b, c = rank_c[g, 0], rank_c[g, 1], rank_c[g, 2]
        rec = torch.cat(
            [
                torch.stack(
                    [
                        (a * dx + b * dy) * dLds,
                        (b * dx + c * dy) * dLds,
                        0.5 * dx * dx * dLds,
                        dx * dy * dLds,
                        0.5 * dy * dy * dLds,
                        G * dLda,
                    ],
                    1,
                ),
                w[:, None] * gC,
            ],
            1,
        )
        out = torch.zeros(M, 6 + NC, dtype=dtype)
        out.index_add_(0, g, rec)
        grads = torch.empty_like(out)
        grads[order] = out
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
