"""Parameters of the reconstruction_quality stage (ReconstructionQualitySettings, load_settings) and its stage name."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..settings import defaults, load, setting

RECONSTRUCTION_QUALITY_STAGE = "reconstruction_quality"


@dataclass(frozen=True)
class ReconstructionQualitySettings:
    """Settings of the reconstruction_quality stage (config section `reconstruction_quality`)."""

    max_frames: int = setting(24, "held-out views at observed times rendered (evenly spaced); 0 = all", minimum=0)
    tracking_neighbors: int = setting(
        4, "Gaussians a ground-truth surface point is attached to for the observed-motion errors", minimum=1
    )


DEFAULT_PARAMS: dict[str, Any] = defaults(ReconstructionQualitySettings)


def load_settings(
    params: Mapping[str, Any] | ReconstructionQualitySettings | None,
) -> ReconstructionQualitySettings:
    """Defaults <- params, checked, as a frozen ReconstructionQualitySettings; unknown keys are refused."""
    return load(ReconstructionQualitySettings, RECONSTRUCTION_QUALITY_STAGE, params)
