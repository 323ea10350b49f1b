"""gsplat backend (CUDA): imported lazily, only when CUDA tensors are rendered.

Maps `mogaf.render.rasterize` onto `gsplat.rasterization` with the same
conventions: one camera, `render_mode="RGB+ED"` (expected depth as the last
channel), `packed=False` (so `meta["means2d"]` is (1, N, 2)), background
composited by us. Differences from the CPU backends: gsplat 1.5 clamps alpha
at 0.999 (ours 0.99, the 3DGS value, as gsplat's development branch), so
pixels where o * exp(-sigma) > 0.99 differ. Projection (the Jacobian's
field-of-view clamp, eps2d), culling, radii, pixel centres, the 1/255
threshold, the 1e-4 transmittance stop and expected depth are gsplat's.
"""

from __future__ import annotations

import torch

from mogaf.errors import MogafError


def gsplat_module():
    """The gsplat module, or None when CUDA or gsplat is unavailable."""
    if not torch.cuda.is_available():
        return None
    try:
        import gsplat  # noqa: PLC0415 (lazy on purpose: may JIT-build CUDA code)
    except Exception:
        return None
    return gsplat if hasattr(gsplat, "rasterization") else None


def render_gsplat(means, quats, scales, opacities, features, viewmat, K, width, height, near, far, eps2d, tile):
    """Returns (features_acc (H,W,C), depth (H,W,1), alpha (H,W,1), means2d_node, means2d (N,2), radii (N,2))."""
    gs = gsplat_module()
    if gs is None:
        raise MogafError("mogaf.render: backend 'gsplat' needs CUDA and an importable gsplat (pip install gsplat)")
    dtype = means.dtype
    f32 = [t.float() for t in (means, quats, scales, opacities, features)]
    means_, quats_, scales_, opac_, feats_ = f32
    # Zero-norm quaternions -> identity (gsplat would divide by zero).
    n2 = (quats_ * quats_).sum(-1, keepdim=True)
    ident = torch.zeros_like(quats_)
    ident[:, 0] = 1.0
    quats_ = torch.where(n2 > 1e-24, quats_, ident)
    colors, alphas, meta = gs.rasterization(
        means_,
        quats_,
        scales_,
        opac_,
        feats_,
        viewmat.float()[None],
        K.float()[None],
        int(width),
        int(height),
        near_plane=float(near),
        far_plane=float(far),
        eps2d=float(eps2d),
        packed=False,
        tile_size=int(tile),
        render_mode="RGB+ED",
        rasterize_mode="classic",
    )
    C = features.shape[1]
    node = meta["means2d"]
    radii = meta["radii"].reshape(means.shape[0], -1)
    if radii.shape[1] == 1:  # gsplat < 1.5: one radius per Gaussian
        radii = radii.expand(-1, 2)
    return (
        colors[0, ..., :C].to(dtype),
        colors[0, ..., C:].to(dtype),
        alphas[0].to(dtype),
        node,
        node.reshape(means.shape[0], 2),
        radii.to(torch.int32).contiguous(),
    )
