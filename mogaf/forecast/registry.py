"""The forecasters by method name: load_settings, make_forecaster, defaults, fit_and_rollout.

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
from mogaf.forecast.params import METHOD_BY_NAME, METHODS


def method_class(method: str) -> type[Forecaster]:
    """The Forecaster class the method table names for `method` (which may
    hand its settings to another: Forecaster.for_settings)."""
    entry = METHOD_BY_NAME.get(method)
    if entry is None:
        raise MogafError(f"forecast: unknown method '{method}' (choose from {', '.join(METHODS)})")
    module, cls = entry.forecaster.split(":")
    return getattr(importlib.import_module(f"mogaf.forecast.{module}"), cls)


def load_settings(method: str, params: Mapping[str, Any] | None) -> Any:
    """`method`'s settings, loaded and checked once: pass them to
    make_forecaster or fit_and_rollout as `params`."""
    return method_class(method).load_settings(params)


def make_forecaster(method: str, params: Any = None, seed: int = 0, device: str = "cpu") -> Forecaster:
    """`params`: a mapping of the method's settings, or what load_settings
    returned; `device`: auto | cpu | cuda, where the torch-based methods compute."""
    cls = method_class(method)
    settings = cls.load_settings(params)
    return cls.for_settings(settings)(settings, seed, device)


def defaults(method: str) -> dict[str, Any]:
    """A copy of the method's DEFAULTS."""
    return dict(method_class(method).DEFAULTS)


def fit_and_rollout(
    method: str,
    observed: np.ndarray,
    n_steps: int,
    params: Any = None,
    seed: int = 0,
    rigid: bool | None = None,
    device: str = "cpu",
) -> ForecastResult:
    """Fit `method` on one group's observed poses for a forecast of n_steps
    and roll it out. `params`: as make_forecaster's; `rigid`: the grouping's
    rigid flag of the group (None: unknown); `device`: auto | cpu | cuda,
    where the torch-based methods compute."""
    fc = make_forecaster(method, params, seed, device)
    fc.fit(observed, rigid=rigid, horizon=n_steps)
    poses = fc.rollout(n_steps)
    return ForecastResult(poses=poses, info=dict(fc.info), bodies=fc.bodies())
