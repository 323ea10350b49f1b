"""The README's timing line, from one `python -m mogaf.bench pipeline --json` file.

It goes between `<!-- timing:start -->` and `<!-- timing:end -->`: the demo's
Snakemake wall time, the machine it was measured on (the file's `results`
field says so) and the slowest budget rows, so that the README states one
measured figure and points at the full table in docs/results.md.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from ..errors import input_error
from .metrics_files import is_number

MARKERS = ("<!-- timing:start -->", "<!-- timing:end -->")


def _minutes(seconds: float) -> str:
    m, s = divmod(int(round(seconds)), 60)
    return f"{m} min {s:02d} s" if m else f"{s} s"


def read_pipeline_rows(path: str | os.PathLike) -> dict[str, Any]:
    """A pipeline benchmark file that has the whole run's wall time."""
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise input_error(p, "no such file") from None
    except (OSError, ValueError) as exc:
        raise input_error(p, f"not a readable JSON file ({exc})") from None
    if not isinstance(data, dict) or not isinstance(data.get("budgets"), list):
        raise input_error(p, "not `python -m mogaf.bench pipeline --json` output (no 'budgets' list)")
    if data.get("snakemake_s") is None:
        raise input_error(p, "has no whole-run wall time ('snakemake_s'): write it with `--run` or --snakemake-seconds")
    if not _seconds(data["snakemake_s"]):
        raise input_error(p, f"'snakemake_s' is {data['snakemake_s']!r}; expected a finite number of seconds >= 0")
    for i, row in enumerate(data["budgets"]):
        if not isinstance(row, dict) or not all(_seconds(row.get(key)) for key in ("wall_s", "budget_s")):
            raise input_error(p, f"budgets[{i}] is {row!r}; expected an object with seconds 'wall_s' and 'budget_s'")
    return data


def _seconds(value: Any) -> bool:
    return is_number(value) and value >= 0


def timing_line(path: str | os.PathLike) -> str:
    """One Markdown paragraph: the demo's wall time and its stages' times against their budgets."""
    data = read_pipeline_rows(path)
    rows = [r for r in data["budgets"] if not str(r.get("row", "")).startswith("Snakemake run")]
    stages = ", ".join(f"{r['row']} {float(r['wall_s']):.0f} s ({float(r['budget_s']):.0f})" for r in rows)
    where = str(data.get("results", "")).strip()
    return (
        f"Measured: the demo's Snakemake run took {_minutes(float(data['snakemake_s']))} "
        f"({where}); the slowest job of each kind against its budget: {stages}. "
        f"From `{Path(path).as_posix()}`; every job in [docs/results.md](docs/results.md).\n"
    )
