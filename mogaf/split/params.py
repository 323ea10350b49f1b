"""The split stage's one parameter: the observation ratio (check_ratio)."""

from __future__ import annotations

import numpy as np

from ..errors import MogafError


def check_ratio(ratio: float) -> float:
    r = float(ratio)
    if not np.isfinite(r) or not (0.0 < r < 1.0):
        raise MogafError(f"observation ratio {ratio!r} is outside (0, 1)")
    return r
