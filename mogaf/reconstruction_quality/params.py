"""Parameters of the reconstruction_quality stage (DEFAULT_PARAMS, _resolve) and its stage name."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..settings import check, defaults, setting

RECONSTRUCTION_QUALITY_STAGE = "reconstruction_quality"


@dataclass(frozen=True)
class ReconstructionQualitySettings:
    """Settings of the reconstruction_quality stage (config section `reconstruction_quality`)."""

    max_frames: int = setting(24, "held-out views at observed times rendered (evenly spaced); 0 = all", minimum=0)


DEFAULT_PARAMS: dict[str, Any] = defaults(ReconstructionQualitySettings)


def _resolve(params: Mapping[str, Any] | None) -> dict[str, Any]:
    return check(ReconstructionQualitySettings, RECONSTRUCTION_QUALITY_STAGE, params)
