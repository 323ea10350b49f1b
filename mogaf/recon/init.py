"""Initialisation of the 4D Gaussians (Shape-of-Motion recipe, re-derived):
`initialise` picks the recipe for the scene.

- Monocular scenes with depth and 2D tracks (iphone layout): init_tracks
  (lifted tracks, velocity clusters, per-cluster Procrustes bases, a short
  track-only fit); its docstring lists the steps.
- Scenes without tracks (D-NeRF layout, or depth without tracks): init_masks
  (a short-window visual hull from the fg masks, bases at identity, optional
  silhouette fit); its docstring lists the steps.

Modules: init_common (InitResult, geometry and Gaussian helpers),
interpolation (over time steps), init_tracks (with tracks and depth),
init_masks (without tracks).
"""

from __future__ import annotations

import numpy as np

from .data import TrainData
from .init_common import InitResult
from .init_masks import _init_without_tracks
from .init_tracks import _init_from_tracks
from .params import load_settings

__all__ = ["InitResult", "initialise"]


def initialise(data: TrainData, params: dict, seed: int) -> InitResult:
    params = load_settings(params)
    rng = np.random.default_rng(seed)
    if data.has_tracks and data.has_depth:
        return _init_from_tracks(data, params, rng, seed)
    return _init_without_tracks(data, params, rng, seed)
