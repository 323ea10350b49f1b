"""`rasterize`: EWA projection + front-to-back compositing, on one of the backends.

cpu:       fused C++ projection and tile compositor, both with analytic backward
           passes (mogaf/render/csrc/rasterize.cpp, built on first use)
torch:     projection in torch autograd (projection.py) + packed-pairs compositor
           with an analytic backward (torch_raster.py); needs no compiler
reference: projection in torch autograd + dense compositor in plain autograd
           (reference.py); O(N x H x W), for tests
gsplat:    gsplat.rasterization on CUDA tensors (gsplat_backend.py)
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch

from mogaf.errors import MogafError
from mogaf.render.projection import project_gaussians

ENV_BACKEND = "MOGAF_RENDER_BACKEND"
BACKENDS = ("auto", "cpu", "torch", "reference", "gsplat")


@dataclass
class RenderOutput:
    """What `rasterize` returns. Gradients flow from features, alpha and depth."""

    features: torch.Tensor  # (H, W, C), background composited
    alpha: torch.Tensor  # (H, W, 1)
    depth: torch.Tensor  # (H, W, 1) expected camera z, sum(w z) / alpha (0 where alpha = 0)
    radii: torch.Tensor  # (N, 2) int32 pixel box half-sizes, 0 for culled Gaussians
    means2d: torch.Tensor  # (N, 2) pixel coordinates (0 for culled Gaussians)
    depths: torch.Tensor  # (N,) camera-space z of every Gaussian
    visible: torch.Tensor  # (N,) bool, radii > 0
    backend: str  # the backend that rendered: "cpu", "torch", "reference" or "gsplat"
    _means2d_node: torch.Tensor | None = None

    def retain_means2d_grad(self) -> bool:
        """Keep d loss / d means2d after backward (read it with `means2d_grad`).

        Returns False (and does nothing) when means2d is not on a graph, e.g.
        under torch.no_grad() or when no input requires grad.
        """
        node = self._means2d_node
        if node is None or not node.requires_grad:
            return False
        node.retain_grad()
        return True

    @property
    def means2d_grad(self) -> torch.Tensor | None:
        """(N, 2) gradient of the loss w.r.t. means2d, after retain_means2d_grad() + backward."""
        node = self._means2d_node
        if node is None or node.grad is None:
            return None
        return node.grad.reshape(self.means2d.shape)


def resolve_backend(backend: str, device: torch.device) -> str:
    """The concrete backend for `backend` ("auto" honours MOGAF_RENDER_BACKEND)."""
    source = ""
    if backend == "auto" and os.environ.get(ENV_BACKEND, "").strip():
        backend = os.environ[ENV_BACKEND].strip().lower()
        source = f" (from {ENV_BACKEND})"
    if backend not in BACKENDS:
        raise MogafError(f"mogaf.render: unknown backend '{backend}'{source} (choose from {', '.join(BACKENDS)})")
    if device.type == "cuda":
        if backend not in ("auto", "gsplat"):
            raise MogafError(f"mogaf.render: backend '{backend}' renders CPU tensors only; got CUDA tensors")
        from mogaf.render.gsplat_backend import (
            gsplat_module,  # local: gsplat is optional (CUDA only); its backend loads only for CUDA tensors
        )

        if gsplat_module() is None:
            raise MogafError("mogaf.render: CUDA tensors need gsplat (pip install gsplat), which is not importable")
        return "gsplat"
    if device.type != "cpu":
        raise MogafError(f"mogaf.render: unsupported device '{device}'")
    if backend == "gsplat":
        raise MogafError("mogaf.render: backend 'gsplat' needs CUDA tensors")
    if backend == "auto":
        from mogaf.render import cpu  # local: a backend module loads only when that backend is picked

        return "cpu" if cpu.load() is not None else "torch"
    return backend


def _check_inputs(means, quats, scales, opacities, features, viewmat, K, width, height):
    N = means.shape[0] if means.dim() == 2 else -1
    expect = {
        "means": (means, (N, 3)),
        "quats": (quats, (N, 4)),
        "scales": (scales, (N, 3)),
        "viewmat": (viewmat, (4, 4)),
        "K": (K, (3, 3)),
    }
    for name, (t, shape) in expect.items():
        if not isinstance(t, torch.Tensor):
            raise MogafError(f"mogaf.render: {name} must be a torch.Tensor, got {type(t).__name__}")
        if tuple(t.shape) != shape:
            raise MogafError(f"mogaf.render: {name} has shape {tuple(t.shape)}, expected {shape}")
    if tuple(opacities.shape) not in ((N,), (N, 1)):
        raise MogafError(f"mogaf.render: opacities has shape {tuple(opacities.shape)}, expected ({N},)")
    if features.dim() != 2 or features.shape[0] != N or features.shape[1] < 1:
        raise MogafError(f"mogaf.render: features has shape {tuple(features.shape)}, expected ({N}, C)")
    if not means.is_floating_point():
        raise MogafError(f"mogaf.render: means must be floating point, got {means.dtype}")
    if int(width) != width or int(height) != height or width < 1 or height < 1:
        raise MogafError(f"mogaf.render: image size {width}x{height} must be positive integers")


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    features: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    background: torch.Tensor | float | None = None,
    backend: str = "auto",
    *,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    tile_size: int | None = None,
) -> RenderOutput:
    """Render N Gaussians (world frame) into one pinhole camera.

    means (N, 3), quats (N, 4) wxyz (any norm; zero-norm = identity), scales (N, 3)
    linear, opacities (N,) in [0, 1], features (N, C) any C, viewmat (4, 4)
    world-to-camera OpenCV, K (3, 3) pixels. `background` (C,) or scalar is
    composited as features + (1 - alpha) * background. Differentiable w.r.t.
    means, quats, scales, opacities, features (and viewmat); not K.
    """
    _check_inputs(means, quats, scales, opacities, features, viewmat, K, width, height)
    width, height = int(width), int(height)
    if tile_size is not None and not 1 <= int(tile_size) <= 64:
        raise MogafError(f"mogaf.render: tile_size {tile_size} must be in [1, 64]")
    name = resolve_backend(backend, means.device)
    if means.dtype in (torch.float16, torch.bfloat16):
        # Half precision in, half precision out; the arithmetic runs in float32.
        out = rasterize(
            *(t.float() if isinstance(t, torch.Tensor) else t for t in (means, quats, scales, opacities, features)),
            viewmat.float(), K.float(), width, height,
            background=background.float() if isinstance(background, torch.Tensor) else background,
            backend=name, near=near, far=far, eps2d=eps2d, tile_size=tile_size,
        )  # fmt: skip
        for field in ("features", "alpha", "depth", "means2d", "depths"):
            setattr(out, field, getattr(out, field).to(means.dtype))
        return out
    if means.shape[0] >= 2**31 - 1:
        raise MogafError(f"mogaf.render: {means.shape[0]} Gaussians exceed the kernel's int32 indices")
    dtype = means.dtype
    quats, scales, features = quats.to(dtype), scales.to(dtype), features.to(dtype)
    opacities = opacities.reshape(-1).to(dtype)
    viewmat = viewmat.to(dtype=dtype, device=means.device)
    K = K.to(dtype=dtype, device=means.device)
    N, C = features.shape
    bg = None
    if background is not None:
        bg = torch.as_tensor(background, dtype=dtype, device=means.device).reshape(-1)
        if bg.numel() not in (1, C):
            raise MogafError(f"mogaf.render: background has {bg.numel()} values, expected 1 or {C}")

    if name == "gsplat":
        from mogaf.render.gsplat_backend import (
            render_gsplat,  # local: gsplat is optional (CUDA only); its backend loads only for CUDA tensors
        )

        feat_img, depth, alpha, node, means2d, radii = render_gsplat(
            means, quats, scales, opacities, features, viewmat, K, width, height, near, far, eps2d, tile_size or 16
        )
        depths = means @ viewmat[2, :3] + viewmat[2, 3]
        visible = (radii > 0).any(-1)
    else:
        if name == "cpu":
            from mogaf.render.cpu import project_cpu  # local: a backend module loads only when that backend is picked

            means2d, conics, depths, radii, visible = project_cpu(
                means, quats, scales, opacities, viewmat, K, width, height, near, far, eps2d
            )
        else:
            proj = project_gaussians(means, quats, scales, opacities, viewmat, K, width, height, near, far, eps2d)
            means2d, conics, depths, radii, visible = proj.means2d, proj.conics, proj.depths, proj.radii, proj.visible
        node = means2d
        if name == "cpu":
            # All N Gaussians go in (culled ones have radii 0): no gather/scatter. The
            # kernel also composites the background and normalises the depth.
            from mogaf.render.cpu import (  # local: a backend module loads only when that backend is picked
                DEFAULT_TILE,
                composite_cpu,
            )

            feat_img, alpha, depth = composite_cpu(
                means2d, conics, opacities, features, depths, radii, width, height, bg, tile_size or DEFAULT_TILE
            )
        else:
            vis_idx = visible.nonzero().squeeze(1)
            z = depths.index_select(0, vis_idx)
            args = (
                means2d.index_select(0, vis_idx),
                conics.index_select(0, vis_idx),
                opacities.index_select(0, vis_idx),
                torch.cat([features.index_select(0, vis_idx), z[:, None]], 1),
                radii.index_select(0, vis_idx),
                z.detach(),
                width,
                height,
            )
            if name == "torch":
                from mogaf.render.torch_raster import (
                    composite_torch,  # local: a backend module loads only when that backend is picked
                )

                acc, alpha = composite_torch(*args)
            else:
                from mogaf.render.reference import (
                    composite_dense,  # local: a backend module loads only when that backend is picked
                )

                acc, alpha = composite_dense(*args)
            feat_img = acc[..., :C]
            depth = acc[..., C:] / alpha.clamp(min=1e-10)
            if bg is not None:
                feat_img = feat_img + (1 - alpha) * bg

    if name == "gsplat" and bg is not None:
        feat_img = feat_img + (1 - alpha) * bg
    return RenderOutput(
        features=feat_img,
        alpha=alpha,
        depth=depth,
        radii=radii,
        means2d=means2d,
        depths=depths,
        visible=visible,
        backend=name,
        _means2d_node=node,
    )
