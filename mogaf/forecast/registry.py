"""The forecasters by method name: make_forecaster, defaults, fit_and_rollout.

The torch-backed modules (gcn, ode, transformer) import torch lazily, inside
their functions, so importing this module stays cheap.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from typing import Any

import numpy as np

from mogaf.errors import MogafError
from mogaf.forecast.base import Forecaster, ForecastResult
from mogaf.forecast.params import METHOD_TABLE, METHODS


def _registry() -> dict[str, type[Forecaster]]:
    """Each method's Forecaster class, from the method table."""
    out = {}
    for method in METHOD_TABLE:
        module, cls = method.forecaster.split(":")
        out[method.name] = getattr(importlib.import_module(f"mogaf.forecast.{module}"), cls)
    return out


def make_forecaster(
    method: str, params: Mapping[str, Any] | None = None, seed: int = 0, device: str = "cpu"
) -> Forecaster:
    """`device`: auto | cpu | cuda, where the torch-based methods compute."""
    reg = _registry()
    if method not in reg:
        raise MogafError(f"forecast: unknown method '{method}' (choose from {', '.join(METHODS)})")
    return reg[method](params, seed, device)


def defaults(method: str) -> dict[str, Any]:
    """A copy of the method's DEFAULTS."""
    reg = _registry()
    if method not in reg:
        raise MogafError(f"forecast: unknown method '{method}' (choose from {', '.join(METHODS)})")
    return dict(reg[method].DEFAULTS)


def fit_and_rollout(
    method: str,
    observed: np.ndarray,
    n_steps: int,
    params: Mapping[str, Any] | None = None,
    seed: int = 0,
    rigid: bool | None = None,
    device: str = "cpu",
) -> ForecastResult:
    """Fit `method` on one group's observed poses and roll out n_steps.
    `rigid`: the grouping's rigid flag of the group (None: unknown);
    `device`: auto | cpu | cuda, where the torch-based methods compute."""
    fc = make_forecaster(method, params, seed, device)
    fc.fit(observed, rigid=rigid)
    poses = fc.rollout(n_steps)
    return ForecastResult(poses=poses, info=dict(fc.info))
