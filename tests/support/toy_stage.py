"""A toy stage for tests/test_stage_runner.py: what a new stage's package
provides (a library function writing its artefact, and a guard), registered
with one StageSpec and run by the generic runner, as the pipeline's are."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from mogaf.artefact import config_digest, read_artefact, write_artefact
from mogaf.errors import input_error
from mogaf.registry import Guard, Input, StageSpec

TOY_STAGE = "toy"


def write_source(path: str | os.PathLike, values: list[float], digest: str = "source") -> Path:
    """An upstream artefact (as ingest would write one)."""
    return write_artefact(path, "ingest", {"values": np.asarray(values, np.float64)}, config_digest=digest)


def run_toy_stage(
    source: str, out: str, params: Mapping[str, Any], *, ratio: str, seed: int, progress: bool = True
) -> Path:
    """The library function: source's values scaled, plus the seed and ratio it got."""
    values = read_artefact(source, "ingest").data["values"] * float(params["scale"])
    data = {"values": values, "seed": np.asarray([seed]), "ratio": np.asarray([float(ratio)])}
    digest = config_digest({"stage": TOY_STAGE, "params": dict(params), "seed": seed, "ratio": ratio})
    return write_artefact(out, TOY_STAGE, data, config_digest=digest, attrs={"progress": progress})


def check_has_values(source: str) -> None:
    """The toy's guard: an empty source has nothing to scale."""
    if not len(read_artefact(source, "ingest").data["values"]):
        raise input_error(source, "holds no values; the toy stage scales at least one")


SPEC = StageSpec(
    TOY_STAGE,
    function="support.toy_stage:run_toy_stage",
    output="toy.h5",
    inputs=(Input("source", "ingest"),),
    settings="toy",
    seed="kwarg",
    wildcards=("ratio",),
    guards=(Guard("support.toy_stage:check_has_values", ("source",)),),
    fixed=(("progress", False),),
    cli="toy",
)
