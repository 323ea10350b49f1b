"""Initialisation of the 4D Gaussians (Shape-of-Motion recipe, re-derived).

Monocular scenes with depth and 2D tracks (iphone layout):
  1. lift every visible track point with the depth map at its pixel (only
     where the depth is valid and the pixel is foreground); fill the other
     frames by linear interpolation in time (nearest value at the ends);
  2. canonical frame = the observed frame with the most lifted track points;
  3. drop outliers (canonical distance to the median above the 95% quantile);
  4. k-means (B clusters) on the per-step velocity directions of the tracks;
     clusters below `init_min_cluster_fraction` of the tracks are dropped,
     so B can end up smaller than asked;
  5. per cluster and observed frame, a weighted Procrustes fit (roma,
     Kabsch) from the canonical positions to that frame's positions gives
     the basis (rotation as continuous 6D, translation); frames with too
     little weight copy the previous (walking away from the canonical frame);
     time steps without a frame are interpolated linearly;
  6. coefficient logits = scale * exp(-d / length), d = distance to each
     cluster's median canonical point;
  7. a short optimisation fits bases, coefficients and canonical means to the
     3D tracks (3D L1 + basis smoothness + coefficient sparsity), no
     rendering;
  8. fg Gaussians = the fitted tracks + points lifted from the canonical
     frame's fg pixels (coefficients copied from the nearest tracks);
     bg Gaussians = background pixels with valid depth, all frames.
Scales: mean distance to the 3 nearest neighbours (fg clamped to its 5-95%
quantiles); opacity 0.7; colour = pixel colour; rotations random.

Scenes without depth (D-NeRF layout): candidates are drawn along the rays of
the canonical frame's fg pixels inside the volume (the dataset point cloud's
bounding box if any, else that of the camera centres) and kept if they fall
in the (dilated) fg masks of most frames within a few time steps of the
canonical one (a short-window visual hull); bases start at identity and
coefficients come from k-means on the canonical positions. Optional bg:
points of the volume that project outside every fg mask.

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

__all__ = ["InitResult", "initialise"]


def initialise(data: TrainData, params: dict, seed: int) -> InitResult:
    rng = np.random.default_rng(seed)
    if data.has_tracks and data.has_depth:
        return _init_from_tracks(data, params, rng, seed)
    return _init_without_tracks(data, params, rng, seed)
