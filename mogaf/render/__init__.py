"""Differentiable Gaussian splatting (3DGS / EWA) for CPU tensors, gsplat on CUDA.

    out = rasterize(means, quats, scales, opacities, features, viewmat, K, W, H)
    out.features (H, W, C), out.alpha (H, W, 1), out.depth (H, W, 1) (expected
    depth, alpha-normalised), out.radii (N, 2) int32, out.means2d (N, 2),
    out.depths (N,) camera z, out.visible (N,) bool.

Screen-space gradient for densification: call `out.retain_means2d_grad()` before
`loss.backward()` and read `out.means2d_grad` (N, 2) after it. On the CPU
backends `out.means2d` is itself on the graph, so `out.means2d.retain_grad()`
works too; on gsplat the graph node is gsplat's `meta["means2d"]` (1, N, 2).

Backends: "cpu" (fused C++ projection + tile compositor with analytic backward
passes, built on first use into cache_dir("kernels")), "torch" (pure torch:
autograd projection + packed-pairs compositor with an analytic backward; no
compiler needed), "reference" (dense all-Gaussians x all-pixels, slow, for
tests), "gsplat" (CUDA), "auto" (gsplat for CUDA tensors, else "cpu", else
"torch" with one warning). MOGAF_RENDER_BACKEND overrides "auto" (e.g. =torch).
Importing this module never builds anything and never imports gsplat.

Semantics (all backends; gsplat differs only in clamping alpha at 0.999): 3DGS /
EWA projection (see projection.py), opacity-aware box radius, alpha =
min(0.99, o exp(-sigma)), pairs with alpha < 1/255 skipped, front-to-back by
camera z (ties by index), a pixel stops before the Gaussian that would bring its
transmittance to <= 1e-4. The result does not depend on the tile size or the
number of threads (the CPU kernel's gradient reduction is deterministic).
"""

from mogaf.render.core import BACKENDS, ENV_BACKEND, RenderOutput, rasterize, resolve_backend
from mogaf.render.projection import Projected, project_gaussians, quat_to_rotmat

__all__ = [
    "BACKENDS",
    "ENV_BACKEND",
    "Projected",
    "RenderOutput",
    "project_gaussians",
    "quat_to_rotmat",
    "rasterize",
    "resolve_backend",
]
