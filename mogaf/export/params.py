"""Settings of the export stage (ExportSettings, load_settings) and where its files go."""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..settings import defaults, load, setting

EXPORT_STAGE = "export"
PLY_FOLDER = "ply"  # the PLY files' folder, beside index.json


@dataclass(frozen=True)
class ExportSettings:
    """Settings of the export stage (config section `export`): 3DGS PLY files of a forecast."""

    steps: list | None = setting(
        None,
        "forecast time steps (scene time-grid indices) written as PLY files; null = every forecast step",
        schema={"items": {"type": "integer", "minimum": 0}, "uniqueItems": True},
    )
    group_id: bool = setting(
        False,
        "add each Gaussian's motion group as a last int32 property `group_id` (-1: static background); "
        "viewers ignore it",
    )
    sh_fit_order: int = setting(
        16,
        "ours: Gauss-Legendre nodes in cos(theta) (twice as many in azimuth) of the sphere quadrature that fits "
        "3DGS's linear SH colour to the model's sigmoid colour when sh_degree > 0 (degree 0 converts exactly); "
        "at least 4, the fewest that keep degree-3 harmonics orthogonal",
        minimum=4,
    )


DEFAULT_PARAMS: dict[str, Any] = defaults(ExportSettings)


def load_settings(params: Mapping[str, Any] | ExportSettings | None) -> ExportSettings:
    """Defaults <- params, checked, as a frozen ExportSettings; unknown keys are refused."""
    return load(ExportSettings, EXPORT_STAGE, params)


def ply_folder(index_json: str | os.PathLike) -> str:
    """The folder of the PLY files that `index_json` lists: `ply/` beside it
    (also for the rule's path pattern, whose wildcards pass through)."""
    return os.path.join(os.path.dirname(os.fspath(index_json)), PLY_FOLDER)
