"""The Gaussians mogaf.rendering draws, as 3DGS splats, and their render.

`model_splats` converts a Model4D once (colours, scales, opacities): its
dynamic Gaussians first, then the static background, the order and the set
that `mogaf.rendering.render_model` / `render_poses` rasterize. `posed_splats`
places the dynamic rows at one time step's poses (a trajectory step or a
forecast step). `render_splats` draws splats as a 3DGS viewer would (colours
from f_dc / f_rest, mogaf.export.colors) with the same rasterizer.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import torch

from ..representation import GaussianSet, Model4D
from .colors import splat_colors, splat_sh
from .ply import SPLAT_ARRAYS, SplatCloud

BACKGROUND_GROUP = -1  # group_id of the static background's Gaussians (no motion group)


def _parts(model: Model4D) -> list[GaussianSet]:
    """The Gaussian sets the renderer draws: dynamic, then the background where it has any."""
    return [model.fg] + ([model.bg] if model.bg is not None and len(model.bg) > 0 else [])


def _set_splats(g: GaussianSet, quadrature_order: int) -> SplatCloud:
    sh_dc, sh_rest = splat_sh(g.color_logits, g.sh_rest, quadrature_order)
    return SplatCloud(
        means=np.asarray(g.means, np.float32),
        quats=np.asarray(g.quats, np.float32),
        log_scales=np.asarray(g.log_scales, np.float32),
        opacity_logits=np.asarray(g.opacity_logits, np.float32).reshape(-1),
        sh_dc=sh_dc.astype(np.float32),
        sh_rest=sh_rest.astype(np.float32),
    )


def model_splats(model: Model4D, *, quadrature_order: int, fg_group_id: np.ndarray | None = None) -> SplatCloud:
    """Every Gaussian the renderer draws, dynamic ones at their canonical
    poses (place them with `posed_splats`). With `fg_group_id` (one motion
    group per dynamic Gaussian) the splats carry group ids, BACKGROUND_GROUP
    for the background."""
    sets = [_set_splats(g, quadrature_order) for g in _parts(model)]
    group_id = None
    if fg_group_id is not None:
        ids = [np.asarray(fg_group_id, np.int64).reshape(-1)] + [np.full(len(s), BACKGROUND_GROUP) for s in sets[1:]]
        group_id = np.concatenate(ids).astype(np.int32)
    return SplatCloud(
        **{key: np.concatenate([getattr(s, key) for s in sets]) for key in SPLAT_ARRAYS},
        group_id=group_id,
    )


def posed_splats(splats: SplatCloud, fg_means: np.ndarray, fg_quats: np.ndarray) -> SplatCloud:
    """`splats` with its first rows (the dynamic Gaussians) at poses (N_fg, 3) / (N_fg, 4 wxyz)."""
    n = int(np.shape(fg_means)[0])
    means, quats = splats.means.copy(), splats.quats.copy()
    means[:n] = np.asarray(fg_means, np.float32)
    quats[:n] = np.asarray(fg_quats, np.float32)
    return dataclasses.replace(splats, means=means, quats=quats)


@torch.no_grad()
def render_splats(
    splats: SplatCloud,
    K: Any,
    w2c: Any,
    width: int,
    height: int,
    background: tuple[float, float, float],
    *,
    backend: str = "auto",
):
    """Render `splats` with mogaf's rasterizer, coloured as 3DGS viewers colour
    them. K (3, 3), w2c (4, 4) OpenCV world-to-camera; returns the rasterizer's output."""
    from ..rendering import camera_center, rasterize  # local: the renderer loads on the first render

    K_t = torch.as_tensor(np.asarray(K), dtype=torch.float32)
    w2c_t = torch.as_tensor(np.asarray(w2c), dtype=torch.float32)
    means = torch.as_tensor(splats.means, dtype=torch.float32)
    colors = splat_colors(splats.sh_dc, splats.sh_rest, means, camera_center(w2c_t))
    return rasterize(
        means.contiguous(),
        torch.as_tensor(splats.quats, dtype=torch.float32).contiguous(),
        torch.exp(torch.as_tensor(splats.log_scales, dtype=torch.float32)).contiguous(),
        torch.sigmoid(torch.as_tensor(splats.opacity_logits, dtype=torch.float32)).contiguous(),
        colors.contiguous(),
        w2c_t,
        K_t,
        int(width),
        int(height),
        background=torch.tensor([float(c) for c in background], dtype=torch.float32),
        backend=backend,
    )
