"""Render a 4D model: dynamic Gaussians at given poses + the static background.

Used wherever a stage renders a stored model (evaluation of forecasts,
grouping quality, reconstruction quality at held-out views). Colours follow
`mogaf.sh`, the convention the reconstruction is trained with.
"""

from __future__ import annotations

import numpy as np
import torch

from .representation import GaussianSet, Model4D
from .sh import gaussian_colors


def _tensor(a: np.ndarray | torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a) if not isinstance(a, torch.Tensor) else a, dtype=dtype)


def gaussians_at(gs: GaussianSet, means: np.ndarray | torch.Tensor, quats: np.ndarray | torch.Tensor, w2c: np.ndarray, degree: int,
                 dtype: torch.dtype = torch.float32) -> dict[str, torch.Tensor]:
    """Activated rasterizer inputs for Gaussians at the given world poses."""
    m = _tensor(means, dtype)
    R = torch.as_tensor(np.asarray(w2c)[:3, :3], dtype=dtype)
    t = torch.as_tensor(np.asarray(w2c)[:3, 3], dtype=dtype)
    centre = -(R.T @ t)
    # degree is the model's; sh_rest carries exactly its bands
    sh = None if gs.sh_rest is None or degree == 0 else _tensor(gs.sh_rest, dtype)
    rgb = gaussian_colors(_tensor(gs.color_logits, dtype), sh, m, centre)
    return {
        "means": m,
        "quats": _tensor(quats, dtype),
        "scales": torch.exp(_tensor(gs.log_scales, dtype)),
        "opacities": torch.sigmoid(_tensor(gs.opacity_logits, dtype)),
        "colors": rgb,
    }


def render_model_at(model: Model4D, fg_means: np.ndarray, fg_quats: np.ndarray, K: np.ndarray, w2c: np.ndarray, width: int, height: int,
                    *, extra_fg_features: np.ndarray | None = None, backend: str = "auto", with_background: bool = True):
    """Render dynamic Gaussians at (fg_means, fg_quats) plus the static background.

    `extra_fg_features` (N_fg, C') are appended as channels after RGB (e.g.
    one-hot group labels); background Gaussians get zeros there.
    Returns the rasterizer output (features (H, W, 3 + C'), alpha, depth).
    """
    from .render import rasterize

    parts = [gaussians_at(model.fg, fg_means, fg_quats, w2c, model.sh_degree)]
    if with_background and model.bg is not None and len(model.bg):
        parts.append(gaussians_at(model.bg, model.bg.means, model.bg.quats, w2c, model.sh_degree))
    cat = {k: torch.cat([p[k] for p in parts]) for k in parts[0]}
    feats = cat["colors"]
    if extra_fg_features is not None:
        extra = torch.as_tensor(np.asarray(extra_fg_features), dtype=feats.dtype)
        pad = torch.zeros((feats.shape[0] - extra.shape[0], extra.shape[1]), dtype=feats.dtype)
        feats = torch.cat([feats, torch.cat([extra, pad])], dim=1)
    bg_color = torch.zeros(feats.shape[1], dtype=feats.dtype)
    bg_color[:3] = torch.as_tensor(model.background, dtype=feats.dtype)
    with torch.no_grad():
        return rasterize(cat["means"], cat["quats"], cat["scales"], cat["opacities"], feats,
                         torch.as_tensor(w2c, dtype=feats.dtype), torch.as_tensor(K, dtype=feats.dtype),
                         int(width), int(height), background=bg_color, backend=backend)


def observed_pose(model: Model4D, timestep: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-Gaussian (means, quats) at an observed time step of the scene grid."""
    idx = np.flatnonzero(model.timesteps == int(timestep))
    if idx.size == 0:
        raise ValueError(f"time step {timestep} is not an observed step of this model ({model.timesteps[0]}..{model.timesteps[-1]})")
    i = int(idx[0])
    return model.trajectory_means[:, i], model.trajectory_quats[:, i]


def to_uint8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.round(np.asarray(img) * 255.0), 0, 255).astype(np.uint8)

