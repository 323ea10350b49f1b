"""Inputs of the evaluation stage: forecast artefacts and Snakemake benchmark files.

read_forecast / _check_forecast (poses of every fg Gaussian at the split's
forecast steps), forecast_summary (what metrics.json keeps of a forecast's
attrs), read_benchmark / runtime_section (wall time and peak memory).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..artefact import read_artefact
from ..errors import input_error
from ..representation import Model4D
from ..split import Split

FORECAST_STAGE = "forecast"


def read_forecast(path: str | os.PathLike) -> dict[str, Any]:
    art = read_artefact(path, FORECAST_STAGE, required=["timesteps", "means", "quats"])
    return {
        "timesteps": np.asarray(art["timesteps"], np.int64),
        "means": art["means"],
        "quats": art["quats"],
        "attrs": art.attrs,
        "path": str(path),
    }


def _check_forecast(fc: dict[str, Any], model: Model4D, split: Split) -> None:
    n = len(model.fg)
    if fc["means"].shape[:1] != (n,) or fc["quats"].shape[:1] != (n,):
        raise input_error(fc["path"], f"forecast has {fc['means'].shape[0]} Gaussians, the model has {n}")
    if not np.array_equal(fc["timesteps"], split.forecast_timesteps):
        raise input_error(fc["path"], "forecast time steps differ from the split's forecast time steps")


def read_benchmark(path: str | os.PathLike) -> dict[str, float]:
    """Wall seconds and peak RSS (MB) from a Snakemake benchmark TSV."""
    import pandas as pd

    p = Path(path)
    try:
        df = pd.read_csv(p, sep="\t")
    except (OSError, ValueError) as exc:
        raise input_error(p, f"not a readable benchmark TSV ({exc.__class__.__name__})") from None
    if "s" not in df.columns or df.empty:
        raise input_error(p, "benchmark TSV lacks the 's' column")
    wall = float(pd.to_numeric(df["s"], errors="coerce").fillna(0).sum())
    rss = pd.to_numeric(df.get("max_rss", pd.Series([np.nan])), errors="coerce").max()
    return {"wall_s": round(wall, 3), "max_rss_mb": None if not np.isfinite(rss) else round(float(rss), 1)}


def forecast_summary(attrs: Mapping[str, Any]) -> dict[str, Any]:
    """What metrics.json keeps of a forecast artefact: no wall-clock values
    (they live in the runtime section), so reruns give identical files."""
    out = {k: attrs[k] for k in ("method", "groupwise", "num_groups_trained", "params", "coherence") if k in attrs}
    jobs = attrs.get("flags") or {}
    out["jobs"] = {
        job: {k: v for k, v in (info or {}).items() if not k.endswith("_time_s")} for job, info in sorted(jobs.items())
    }
    return out


def runtime_section(benchmarks: Mapping[str, str], methods: list[str]) -> dict[str, Any]:
    stages = {name: read_benchmark(path) for name, path in sorted(benchmarks.items())}
    shared = sum(v["wall_s"] for k, v in stages.items() if not k.startswith("forecast_"))
    per_method = {}
    for m in methods:
        own = sum(v["wall_s"] for k, v in stages.items() if k == f"forecast_{m}" or k.startswith(f"forecast_{m}_group"))
        per_method[m] = round(shared + own, 3)
    return {"stages": stages, "total_wall_s": per_method}
