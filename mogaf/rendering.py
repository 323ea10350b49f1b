"""Rendering a stored 4D Gaussian model (the one place that assembles a
Model4D into rasterizer inputs).

`render_model` draws a Model4D at one of its observed time steps from any
camera; `render_poses` draws the dynamic Gaussians at explicit per-Gaussian
poses (e.g. forecast ones) together with the static background. Both go
through mogaf.render.rasterize (any feature width in one pass). Used by the
evaluation (forecast renders, held-out reconstruction quality), the grouping
quality (one-hot group labels as features) and the recon benchmark. Colours
follow `mogaf.sh`, the convention the reconstruction is trained with; the
differentiable training render is `mogaf.recon.trainer.Trainer.render_frame`.

features:
  "rgb"       -> (H, W, 3) colours composited on the model's background colour
  "rgb+mask"  -> 4 channels: colour and the fg share (1 for dynamic Gaussians,
                 0 for background ones; composited on 0)
  an array    -> (N_fg + N_bg, C) custom per-Gaussian features (fg rows first),
                 composited on 0 (e.g. one-hot group ids for grouping)
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from .errors import MogafError
from .representation import GaussianSet, Model4D
from .sh import gaussian_colors


def rasterize(*args: Any, **kwargs: Any):
    """mogaf.render.rasterize, imported late (the renderer is a separate package)."""
    from .render import rasterize as _rasterize  # local: the renderer is a separate package, loaded on the first render

    return _rasterize(*args, **kwargs)


def _t(x: Any, dtype=torch.float32) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.to(dtype)
    return torch.as_tensor(np.asarray(x), dtype=dtype)


def camera_center(w2c: torch.Tensor) -> torch.Tensor:
    R, t = w2c[:3, :3], w2c[:3, 3]
    return -(R.T @ t)


def _set_colors(g: GaussianSet, means: torch.Tensor, cam: torch.Tensor) -> torch.Tensor:
    sh = None if g.sh_rest is None else _t(g.sh_rest)
    return gaussian_colors(_t(g.color_logits), sh, means, cam)


def _render_sets(
    fg: GaussianSet,
    fg_means: torch.Tensor,
    fg_quats: torch.Tensor,
    bg: GaussianSet | None,
    K: Any,
    w2c: Any,
    width: int,
    height: int,
    features: Any,
    background: tuple[float, float, float],
    backend: str,
):
    K_t, w2c_t = _t(K), _t(w2c)
    cam = camera_center(w2c_t)
    means = [fg_means]
    quats = [fg_quats]
    log_scales = [_t(fg.log_scales)]
    opac = [_t(fg.opacity_logits)]
    sets = [(fg, fg_means)]
    if bg is not None and len(bg) > 0:
        means.append(_t(bg.means))
        quats.append(_t(bg.quats))
        log_scales.append(_t(bg.log_scales))
        opac.append(_t(bg.opacity_logits))
        sets.append((bg, _t(bg.means)))
    n_fg = fg_means.shape[0]
    n_all = sum(m.shape[0] for m in means)
    if isinstance(features, str):
        if features not in ("rgb", "rgb+mask"):
            raise MogafError(f"render: unknown features {features!r} (use 'rgb', 'rgb+mask' or an (N, C) array)")
        cols = torch.cat([_set_colors(g, m, cam) for g, m in sets], dim=0)
        bgc = torch.tensor([float(c) for c in background], dtype=torch.float32)
        if features == "rgb+mask":
            is_fg = torch.zeros(n_all, 1)
            is_fg[:n_fg] = 1.0
            cols = torch.cat([cols, is_fg], dim=1)
            bgc = torch.cat([bgc, torch.zeros(1)])
        feats = cols
    else:
        feats = _t(features)
        if feats.ndim != 2 or feats.shape[0] != n_all:
            raise MogafError(
                f"render: custom features must be ({n_all}, C) (fg rows then bg rows), got {tuple(feats.shape)}"
            )
        bgc = torch.zeros(feats.shape[1])
    return rasterize(
        torch.cat(means, 0).contiguous(),
        torch.cat(quats, 0).contiguous(),
        torch.exp(torch.cat(log_scales, 0)).contiguous(),
        torch.sigmoid(torch.cat(opac, 0)).contiguous(),
        feats.contiguous(),
        w2c_t,
        K_t,
        int(width),
        int(height),
        background=bgc,
        backend=backend,
    )


def _background(model: Model4D, background: Any) -> tuple[float, float, float]:
    # float(): attrs written through mogaf.artefact may come back as decimal strings
    src = model.background if background is None else background
    return tuple(float(c) for c in src)  # type: ignore[return-value]


def timestep_position(model: Model4D, timestep: int) -> int:
    hits = np.flatnonzero(np.asarray(model.timesteps) == int(timestep))
    if hits.size == 0:
        steps = np.asarray(model.timesteps)
        raise MogafError(
            f"render: time step {timestep} is not an observed step of the model ({steps.min()}..{steps.max()})"
        )
    return int(hits[0])


@torch.no_grad()
def render_model(
    model: Model4D,
    timestep: int,
    K: Any,
    w2c: Any,
    width: int,
    height: int,
    *,
    features: Any = "rgb",
    background: tuple[float, float, float] | None = None,
    backend: str = "auto",
):
    """Render `model` at scene time step `timestep` (one of model.timesteps).

    Dynamic Gaussians take their stored trajectory pose at that step; the
    background is static. K, w2c: (3,3), (4,4) OpenCV world-to-camera.
    Returns the rasterizer's output (features (H,W,C), alpha, depth, ...).
    """
    k = timestep_position(model, timestep)
    means = _t(model.trajectory_means[:, k])
    quats = _t(model.trajectory_quats[:, k])
    bgc = _background(model, background)
    return _render_sets(model.fg, means, quats, model.bg, K, w2c, width, height, features, bgc, backend)


@torch.no_grad()
def render_poses(
    model: Model4D,
    means: Any,
    quats: Any,
    K: Any,
    w2c: Any,
    width: int,
    height: int,
    *,
    features: Any = "rgb",
    background: tuple[float, float, float] | None = None,
    backend: str = "auto",
):
    """Render the dynamic Gaussians at explicit poses (N_fg,3)/(N_fg,4 wxyz) + the static background."""
    m, q = _t(means), _t(quats)
    n = len(model.fg)
    if m.shape != (n, 3) or q.shape != (n, 4):
        raise MogafError(
            f"render_poses: expected means ({n}, 3) and quats ({n}, 4), got {tuple(m.shape)} and {tuple(q.shape)}"
        )
    if not (torch.isfinite(m).all() and torch.isfinite(q).all()):
        raise MogafError("render_poses: poses have non-finite values")
    bgc = _background(model, background)
    return _render_sets(model.fg, m, q, model.bg, K, w2c, width, height, features, bgc, backend)
