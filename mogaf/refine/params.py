"""Parameters of the refine stage: REFINE_DEFAULTS, the reconstruction settings
refinement always overrides (FIXED_RECON) and resolve_params."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..errors import MogafError
from ..recon.params import resolve_params as resolve_recon_params
from ..settings import check, defaults, setting


@dataclass(frozen=True)
class RefineSettings:
    """Settings of the refine stage (config section `refine`)."""

    iterations: int = setting(400, "CPU budget (paper: SoM's schedule continued; not stated)", minimum=0)
    lambda_rigid: float = setting(0.1, 'supp. "Refinement of 4DGS Representation"', minimum=0)
    lambda_nr: float = setting(0.02, 'supp. "Refinement of 4DGS Representation"', minimum=0)
    rigid_times: int = setting(4, "observed steps sampled per iteration for L_rigid (ours)", minimum=1)
    rigid_members: int = setting(4096, "Gaussians sampled per rigid group and iteration (ours)", minimum=1)
    nr_neighbors: int = setting(8, "|NN(g)| (ours; SoM-style KNN)", minimum=1)
    nr_radius_factor: float = setting(3.0, "fixed radius = this x median 1-NN distance of the group (ours)", minimum=0)
    learn_rigid_motion: bool = setting(
        True, "optimise (R^k_t, t^k_t) together with the bases (False: anchors stay fixed)"
    )
    recon: dict = setting(
        {"lr_boost": 1.0},
        "overrides of the reconstruction parameters used for L_recon (the rest: those of recon.h5). Fine-tuning runs "
        "at SoM's learning rates, without recon's x4 CPU boost: it starts from a fitted model, which larger steps degrade",
        schema={"$ref": "#/definitions/recon"},
    )


REFINE_DEFAULTS: dict[str, Any] = defaults(RefineSettings)

# Reconstruction settings that refinement always overrides: no density control
# (keeps the Gaussian set, and so the group ids), no curriculum or silhouette
# warm-up (those are for starting from scratch), one resolution level.
FIXED_RECON = {
    "stop_control_fraction": 0.0,
    "curriculum": "off",
    "silhouette": "off",
    "coarse_fraction": 0.0,
    "iterations_scale": 1.0,
}


def resolve_params(params: Mapping[str, Any] | None, recon_params: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """REFINE_DEFAULTS <- params; 'recon' = recon.h5's parameters <- overrides <- FIXED_RECON."""
    params = dict(params or {})
    device = params.pop("device", None)
    p = check(RefineSettings, "refine", params)
    for key in ("lambda_rigid", "lambda_nr", "nr_radius_factor"):
        if not math.isfinite(p[key]):
            raise MogafError(f"refine param '{key}' must be a finite number >= 0, got {p[key]!r}")
    base = {k: v for k, v in dict(recon_params or {}).items() if k != "iterations_scale"}
    overrides = dict(p["recon"] or {})
    if device is not None:
        overrides["device"] = device
    rp = resolve_recon_params({**base, **overrides, **FIXED_RECON})
    rp["iterations"] = max(p["iterations"], 1)
    p["recon"] = rp
    return p
