"""Parameters of the evaluation stage: EvaluateSettings (DEFAULT_PARAMS as a dict) and load_settings."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..settings import defaults, load, setting


@dataclass(frozen=True)
class EvaluateSettings:
    """Settings of the evaluate stage (config section `evaluate`)."""

    lpips: bool = setting(True, "AlexNet LPIPS (paper Tables 1-2)")
    save_renders: bool = setting(True, "PNG per evaluation view and method")
    video: bool = setting(True, "GT | forecast | error video per method")
    video_fps: int = setting(8, "frames per second of the GT / forecast / error videos", minimum=1)
    video_min_width: int = setting(
        320,
        "videos: panels narrower than this (px) are enlarged by an integer factor, nearest neighbour; 0 = never",
        minimum=0,
    )
    video_error_max: float = setting(
        0.5, "videos: mean absolute RGB error at the top of the error panel's colour scale", exclusive_minimum=0
    )
    tracking_neighbors: int = setting(4, "Gaussians a GT point is attached to")
    tracking_scale: float = setting(1.0, "scene units -> metres for delta_3D (SoM evaluates in metres)")
    aj_thresholds: list = setting(
        [4, 8, 16, 32, 64], "px; SoM's evaluation (paper follows SoM's protocol)", schema={"items": {"type": "number"}}
    )
    delta_thresholds: list = setting(
        [4, 8, 16, 32, 64], "px, issue/SoM delta_avg", schema={"items": {"type": "number"}}
    )
    visibility_tolerance: float = setting(0.03, "relative depth slack for predicted visibility")
    runtime_in_metrics: bool = setting(True, "wall time / memory in metrics.json (off: byte-identical reruns)")


DEFAULT_PARAMS: dict[str, Any] = defaults(EvaluateSettings)


def load_settings(params: Mapping[str, Any] | EvaluateSettings | None) -> EvaluateSettings:
    """Defaults <- params, checked, as a frozen EvaluateSettings (what the stage reads); unknown keys are refused."""
    return load(EvaluateSettings, "evaluate", params)
