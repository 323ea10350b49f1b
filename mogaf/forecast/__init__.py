"""Group-wise motion forecasting: the MoGaF forecaster and its baselines.

Input: one group's observed trajectories, float64 (G, T, 7) on a uniform time
grid, x_t = [mu_t (3), q_t (4, wxyz unit quaternion, world orientation)].
Output: (G, n_steps, 7) poses at the next n_steps timesteps.

    result = fit_and_rollout("mogaf", observed, n_steps, params={}, seed=0)
    result.poses, result.info

Methods (each with a DEFAULTS mapping naming the source of every value):
    mogaf              MoGaF; by default structure-aware (mogaf.forecast.structured),
                       `mode: paper` gives the paper's transformer forecaster
                       exactly (LW; num_layers=5 -> HC)
    mogaf_paper        the paper's forecaster beside the default: MoGaF with
                       `mode: paper`, reading forecast.mogaf's settings
    gcn                GaussianPrediction-style GCN_xyzr on control points
    ode                ODE-GS-style transformer-encoder latent ODE
    constant_velocity  constant body-frame twist of the last two poses
    frozen             the last observed pose, repeated

Every method sign-canonicalises its input quaternions first, so q -> -q in the
observation never changes a prediction. Torch-based methods are deterministic
on CPU for a given seed (forked RNG, deterministic kernels).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from mogaf.errors import MogafError
from mogaf.forecast.base import ForecastResult, Forecaster
from mogaf.forecast.classical import ConstantVelocity, Frozen

__all__ = [
    "METHODS",
    "ForecastResult",
    "Forecaster",
    "defaults",
    "fit_and_rollout",
    "make_forecaster",
    "param_section",
    "section_params",
]


def _registry() -> dict[str, type[Forecaster]]:
    # The torch-backed modules import torch lazily, so this stays cheap.
    from mogaf.forecast.gcn import GCNForecaster
    from mogaf.forecast.ode import LatentODEForecaster
    from mogaf.forecast.transformer import MoGaFForecaster, MoGaFPaperForecaster

    return {
        "mogaf": MoGaFForecaster,
        "mogaf_paper": MoGaFPaperForecaster,
        "gcn": GCNForecaster,
        "ode": LatentODEForecaster,
        "constant_velocity": ConstantVelocity,
        "frozen": Frozen,
    }


METHODS: tuple[str, ...] = ("mogaf", "mogaf_paper", "gcn", "ode", "constant_velocity", "frozen")

# Methods whose settings live in another method's config section, the
# settings they fix whatever that section says, and those of the section they
# do not read (so changing those reruns nothing of theirs).
PARAM_SECTIONS: dict[str, str] = {"mogaf_paper": "mogaf"}
FIXED_PARAMS: dict[str, dict[str, Any]] = {"mogaf_paper": {"mode": "paper"}}
UNREAD_PARAMS: dict[str, tuple[str, ...]] = {"mogaf_paper": ("structured",)}


def section_params(method: str, section: Mapping[str, Any] | None) -> dict[str, Any]:
    """What `method` reads of its config section (forecast.<param_section(method)>)."""
    unread = UNREAD_PARAMS.get(method, ())
    return {**{k: v for k, v in dict(section or {}).items() if k not in unread}, **FIXED_PARAMS.get(method, {})}


def param_section(method: str) -> str:
    """The `forecast.<section>` holding `method`'s settings."""
    return PARAM_SECTIONS.get(method, method)


def make_forecaster(method: str, params: Mapping[str, Any] | None = None, seed: int = 0) -> Forecaster:
    reg = _registry()
    if method not in reg:
        raise MogafError(f"forecast: unknown method '{method}' (choose from {', '.join(METHODS)})")
    return reg[method](params, seed)


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
) -> ForecastResult:
    """Fit `method` on one group's observed poses and roll out n_steps.
    `rigid`: the grouping's rigid flag of the group (None: unknown)."""
    fc = make_forecaster(method, params, seed)
    fc.fit(observed, rigid=rigid)
    poses = fc.rollout(n_steps)
    return ForecastResult(poses=poses, info=dict(fc.info))
