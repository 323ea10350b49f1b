"""docs/results.md: every measured result of the docs, generated from the
committed benchmark rows (and any metrics.json files given).

    python -m mogaf.report results --write docs/results.md [METRICS.json ...]
    python -m mogaf.report results --check docs/results.md [METRICS.json ...]

Reads every JSON file of `results/bench/` (--bench DIR):

* rows of `python -m mogaf.bench forecast --json` (a "rows" list): the files
  whose methods ran at their defaults or their papers' budgets make the main
  ground-truth table (`mogaf.bench._forecast_report.markdown_report`); files
  with a step budget (`forecast.{gcn,ode}.steps`) a second one beside them, on
  the sets they ran; files with other settings of a method (e.g. a
  `forecast.mogaf.structured` variant) a column each beside that method's
  default;
* rows of `python -m mogaf.bench pipeline --json` ("budgets" and "jobs"): its
  tables (`mogaf.bench.pipeline.render`);
* scene-rows files of `python -m mogaf.report scenes --json` ("scenes"): the
  per-scene tables of a pipeline run over many scenes (`mogaf.report.scenes`),
  e.g. the scene family.

metrics.json files add the glance and per-scene tables (mogaf.report.glance,
mogaf.report.scenes). The page names the command and every file it was made
from; every number on it comes from those files.
"""

from __future__ import annotations

import glob as _glob
import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ..artefact import atomic_path
from ..errors import input_error
from ..paths import read_text_file

BENCH_DIR = Path("results/bench")
REFERENCES = ("constant_velocity", "frozen")  # what the win counts compare against


# ------------------------------------------------------------------ reading
# A scene-rows file read and checked once: (path, where it was measured, its results).
SceneRows = tuple[Path, str, list[dict[str, Any]]]


def read_bench_dir(
    bench_dir: str | os.PathLike,
) -> tuple[list[tuple[Path, dict[str, Any]]], list[Path], list[SceneRows]]:
    """(forecast files with their headers, pipeline files, scene-rows files read) of `bench_dir`, by name."""
    from ..bench._forecast_report import read_rows
    from .scenes import SCENE_ROWS, read_scene_rows

    forecast, pipeline, scenes = [], [], []
    paths = sorted(Path(bench_dir).glob("*.json"))
    if not paths:
        raise input_error(bench_dir, "holds no benchmark .json file")
    for path in paths:
        doc = _load_json(path)
        if "rows" in doc:
            forecast.append((path, read_rows(path)[0]))
        elif "budgets" in doc and "jobs" in doc:
            pipeline.append(path)
        elif SCENE_ROWS in doc:
            scenes.append((path, *read_scene_rows(path)))
        else:
            raise input_error(
                path,
                "is none of `python -m mogaf.bench forecast --json`, `python -m mogaf.bench pipeline --json` "
                "and `python -m mogaf.report scenes --json` output",
            )
    return forecast, pipeline, scenes


def _load_json(path: Path) -> dict[str, Any]:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise input_error(path, f"cannot be read as JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise input_error(path, "is not a JSON object")
    return doc


def changed_params(header: Mapping[str, Any], method: str) -> dict[str, Any]:
    """A method's parameters in a forecast file beyond its defaults: what the
    run changed, leaving out the thread count, a --budget cpu baseline's
    shortening (REDUCED) and a step budget (`steps`), which have their own columns."""
    from ..bench._forecast_report import REDUCED

    params = dict((header.get("params") or {}).get(method) or {})
    params.pop("num_threads", None)
    params.pop("steps", None)
    if header.get("budget") == "cpu":
        for key, value in REDUCED.get(method, {}).items():
            if params.get(key) == value:
                params.pop(key)
    return params


def _methods(header: Mapping[str, Any]) -> list[str]:
    return sorted(header.get("params") or {})


def _steps(header: Mapping[str, Any], method: str) -> int:
    """A method's step budget in a forecast file (forecast.<method>.steps; 0: none)."""
    return int(((header.get("params") or {}).get(method) or {}).get("steps") or 0)


def _has_steps(header: Mapping[str, Any]) -> bool:
    return any(_steps(header, m) > 0 for m in _methods(header))


def classify(files: Sequence[tuple[Path, Mapping[str, Any]]]) -> dict[str, list[Path]]:
    """The forecast files by the table they go to: "main" (every method at its
    defaults or its paper's budget), "steps" (a baseline at a step budget) and
    "variant" (a method with other settings)."""
    out: dict[str, list[Path]] = {"main": [], "steps": [], "variant": []}
    for path, header in files:
        if any(changed_params(header, m) for m in _methods(header)):
            out["variant"].append(path)
        elif _has_steps(header):
            out["steps"].append(path)
        else:
            out["main"].append(path)
    return out


def variant_label(path: Path) -> str:
    """A variant file's column label: its name without `forecast_gt_` ('combine_select')."""
    return path.stem.removeprefix("forecast_gt_")


def _posix(path: str | os.PathLike) -> str:
    return Path(path).as_posix()


def _sources(paths: Sequence[Path]) -> str:
    return ", ".join(f"`{_posix(p)}`" for p in paths)


# ------------------------------------------------------------------ sections
def inputs_table(
    files: Sequence[tuple[Path, Mapping[str, Any]]],
    pipeline: Sequence[Path],
    metrics: Sequence[str | os.PathLike] = (),
    scenes: Sequence[SceneRows] = (),
) -> str:
    """A row per forecast benchmark file: budget, device, seed, the code its rows
    were computed by (mogaf.bench.forecast.code_digest; '–': older files), rows
    and what it changed; a row per pipeline file, per scene-rows file and per
    metrics.json."""
    from ..bench._forecast_report import code_of, read_rows

    lines = [
        "| file | written by | budget | device | seed | code | rows | settings beyond the defaults |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for path, header in files:
        changed = {m: changed_params(header, m) for m in _methods(header)}
        notes = [f"{m}: `{json.dumps(p, sort_keys=True)}`" for m, p in changed.items() if p]
        notes += [f"{m}: steps {_steps(header, m)}" for m in _methods(header) if _steps(header, m)]
        lines.append(
            f"| `{_posix(path)}` | `python -m mogaf.bench forecast --json` | {header.get('budget', '–')} | "
            f"{header.get('device', '–')} | {header.get('seed', '–')} | {code_of(header)} | "
            f"{len(read_rows(path)[1])} | "
            f"{'; '.join(notes) or '–'} |"
        )
    for path in pipeline:
        lines.append(f"| `{_posix(path)}` | `python -m mogaf.bench pipeline --json` | – | – | – | – | – | – |")
    for path, _, results in scenes:
        lines.append(
            f"| `{_posix(path)}` | `python -m mogaf.report scenes --json` | – | – | – | – | {len(results)} | – |"
        )
    for path in metrics:
        lines.append(f"| `{_posix(path)}` | the pipeline's evaluate stage | – | – | – | – | – | – |")
    return "\n".join(lines)


def marked(tag: str, block: str) -> str:
    """`block` between `<!-- tag -->` and `<!-- /tag -->` lines."""
    return f"<!-- {tag} -->\n{block}\n<!-- /{tag} -->"


def main_forecast_section(main: Sequence[Path]) -> str:
    from ..bench._forecast_report import markdown_report

    return "\n\n".join(
        [
            "## Forecasts on ground-truth trajectories",
            "Future 3D EPE (m) per trajectory set and observation ratio, the lowest in bold; `train s`: "
            "wall-clock training seconds per group (for MoGaF the backtest included). Then the mean EPE over the "
            "rows every method has with the win counts against constant velocity and frozen, and the EPE at the "
            "first, middle and last forecast step. `python -m mogaf.bench forecast --summary` with `--from-json` "
            f"{_sources(main)}:",
            marked("forecast-gt-table", markdown_report(main)),
        ]
    )


def steps_forecast_section(main: Sequence[Path], steps: Sequence[Path]) -> str:
    """The step-budget files beside the main files that share a method with
    them or hold the methods that are no baseline, on the sets they ran."""
    from ..bench._forecast_report import REDUCED, markdown_report, read_rows

    budgeted = {m for p in steps for m in _methods(read_rows(p)[0])}
    beside = [p for p in main if any(m in budgeted or m not in REDUCED for m in _methods(read_rows(p)[0]))]
    sets = sorted({str(r["set"]) for p in steps for r in read_rows(p)[1]})
    only = [_glob.escape(s) for s in sets]
    files = [*beside, *steps]
    return "\n\n".join(
        [
            "## Baselines at a step budget",
            "A baseline trained for the fewest whole epochs that give each group at least N optimiser steps "
            "(`forecast.{gcn,ode}.steps: N`, column `method@N`) beside its paper budget, on the sets "
            f"{', '.join(f'`{s}`' for s in sets)}; `--from-json` {_sources(files)}:",
            marked("forecast-gt-ode-steps-table", markdown_report(files, only)),
        ]
    )


def _epe_cells(
    main: Sequence[Path], variants: Sequence[Path]
) -> tuple[list[str], dict[tuple[str, float], dict[str, float]], dict[Path, Any], dict[Path, Any]]:
    """(columns, (set, ratio) -> column -> EPE, the main files used and the
    variant files, each -> its header): each varied method at its defaults,
    its variants and the references."""
    from ..bench._forecast_report import read_rows

    varied: list[str] = []
    columns: list[str] = []
    cells: dict[tuple[str, float], dict[str, float]] = {}
    variant_headers: dict[Path, Any] = {}
    for path in variants:
        header, rows = read_rows(path)
        variant_headers[path] = header
        for r in rows:
            method = str(r["method"])
            if not changed_params(header, method):
                continue
            col = f"{method} ({variant_label(path)})"
            cells.setdefault((str(r["set"]), float(r["ratio"])), {})[col] = float(r["epe"])
            if method not in varied:
                varied.append(method)
            if col not in columns:
                columns.append(col)
    used: dict[Path, Any] = {}
    for path in main:
        header, rows = read_rows(path)
        for r in rows:
            key = (str(r["set"]), float(r["ratio"]))
            if key in cells and (r["method"] in varied or r["method"] in REFERENCES):
                cells[key][str(r["method"])] = float(r["epe"])
                used.setdefault(path, header)
    refs = [m for m in REFERENCES if any(m in row for row in cells.values())]
    return [*varied, *columns, *refs], cells, used, variant_headers


def epe_table(columns: Sequence[str], cells: Mapping[tuple[str, float], Mapping[str, float]]) -> str:
    """A line per (set, ratio), the EPE of each column, the lowest in bold."""
    lines = ["| set | ratio | " + " | ".join(f"{c} EPE" for c in columns) + " |", "|" + "---|" * (2 + len(columns))]
    for (name, ratio), row in cells.items():
        finite = [v for v in row.values() if math.isfinite(v)]
        best = min(finite) if finite else None
        out = [name, f"{ratio:.2f}"]
        for c in columns:
            v = row.get(c)
            out.append("–" if v is None else (f"**{v:.4f}**" if v == best else f"{v:.4f}"))
        lines.append("| " + " | ".join(out) + " |")
    return "\n".join(lines)


def epe_summary(columns: Sequence[str], cells: Mapping[tuple[str, float], Mapping[str, float]]) -> str:
    """Per column: the mean EPE over the rows every column has, and on how many
    of its rows it beats each reference."""
    shared = [k for k, row in cells.items() if all(c in row for c in columns)]
    refs = [a for a in REFERENCES if a in columns]
    head = ["column", f"mean EPE ({len(shared)} rows with every column)"] + [f"beats {a}" for a in refs]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    means = {c: sum(cells[k][c] for k in shared) / len(shared) if shared else math.nan for c in columns}
    best = min((v for v in means.values() if math.isfinite(v)), default=None)
    for c in columns:
        mean = (
            "–" if not math.isfinite(means[c]) else (f"**{means[c]:.4f}**" if means[c] == best else f"{means[c]:.4f}")
        )
        out = [c, mean]
        for a in refs:
            both = [k for k, row in cells.items() if c in row and a in row]
            wins = sum(cells[k][c] < cells[k][a] for k in both)
            out.append("–" if c == a or not both else f"{wins} of {len(both)} ({100.0 * wins / len(both):.0f} %)")
        lines.append("| " + " | ".join(out) + " |")
    return "\n".join(lines)


def variants_section(main: Sequence[Path], variants: Sequence[Path]) -> str:
    from ..bench._forecast_report import code_note

    columns, cells, used, variant_headers = _epe_cells(main, variants)
    notes = []
    for path, header in variant_headers.items():
        for m in _methods(header):
            if changed_params(header, m):
                notes.append(
                    f"- `{m} ({variant_label(path)})`: `{_posix(path)}`, `forecast.{m}` settings "
                    f"`{json.dumps(changed_params(header, m), sort_keys=True)}` over the defaults"
                )
    return "\n\n".join(
        [
            "## Settings of a forecaster against its defaults",
            "The same trajectories, each variant a column beside the method at its defaults "
            f"({_sources(list(used))}); future 3D EPE (m), the lowest in bold:",
            "\n".join(notes),
            epe_table(columns, cells),
            epe_summary(columns, cells),
            *filter(None, [code_note({**used, **variant_headers})]),
        ]
    )


def pipeline_section(path: Path) -> str:
    """The tables of `python -m mogaf.bench pipeline` from its --json rows."""
    from ..bench.pipeline import Job, render, schedule_line

    doc = _load_json(path)
    try:
        jobs = [Job(**j) for j in doc["jobs"]]
        rows = list(doc["budgets"])
        text = render(jobs, rows)
        imports = doc.get("imports_s") or {}
        tail = (
            ["", "A fresh process there: " + ", ".join(f"{k} {v:.2f} s" for k, v in imports.items())] if imports else []
        )
        if doc.get("schedule"):
            tail += ["", schedule_line(doc["schedule"], doc.get("snakemake_s"))]
    except (AttributeError, KeyError, TypeError, ValueError) as exc:
        raise input_error(path, f"is not `python -m mogaf.bench pipeline --json` output ({exc})") from None
    return "\n\n".join(
        [
            f"## Where a pipeline run's time goes: `{_posix(path)}`",
            f"The run: {doc.get('results', '–')}. Wall and CPU time per job against its budget "
            "(`python -m mogaf.bench pipeline`):",
            "\n".join([text, *tail]),
        ]
    )


def scenes_section(rows: SceneRows) -> str:
    """The per-scene tables of a scene-rows file (`python -m mogaf.report scenes --json`)."""
    from .scenes import scenes_table

    path, run, results = rows
    return "\n\n".join(
        [
            f"## Forecasts per scene: `{_posix(path)}`",
            f"The run: {run}. Image metrics at held-out views of the forecast frames (and the tracking EPE in "
            "metres where every scene has ground-truth tracks), the best per row in bold; the mean over the "
            "scenes; MoGaF's PSNR against the better of the two forecasts that learn nothing; what the grouping "
            "and the reconstruction gave (`python -m mogaf.report scenes`):",
            scenes_table(results).rstrip("\n"),
        ]
    )


def metrics_section(metrics_files: Sequence[str | os.PathLike]) -> str:
    from .glance import glance_table
    from .metrics_files import load_metrics
    from .scenes import scenes_table

    results = load_metrics(list(metrics_files))
    return "\n\n".join(
        [
            "## Pipeline results (metrics.json)",
            "Image metrics at held-out views of the forecast frames, tracking EPE in metres "
            "(`python -m mogaf.report glance`):",
            glance_table(results).rstrip("\n"),
            "Per scene (`python -m mogaf.report scenes`):",
            scenes_table(results).rstrip("\n"),
        ]
    )


# ------------------------------------------------------------------ the page
def command(
    target: str | os.PathLike, bench_dir: str | os.PathLike = BENCH_DIR, metrics: Sequence[str | os.PathLike] = ()
) -> str:
    """The command that writes the page to `target` from these inputs."""
    parts = ["python -m mogaf.report results"]
    if Path(bench_dir) != BENCH_DIR:
        parts.append(f"--bench {_posix(bench_dir)}")
    parts += [_posix(m) for m in metrics] + [f"--write {_posix(target)}"]
    return " ".join(parts)


def results_page(
    target: str | os.PathLike, bench_dir: str | os.PathLike = BENCH_DIR, metrics: Sequence[str | os.PathLike] = ()
) -> str:
    """The whole page (Markdown, ending in a newline) that `target` should hold."""
    files, pipeline, scenes = read_bench_dir(bench_dir)
    kinds = classify(files)
    sections = [
        "# Measured results",
        f"Generated by `{command(target, bench_dir, metrics)}` from the files below; do not edit it by hand "
        f"(`--check {_posix(target)}` in place of `--write` exits 1 when the page is not what they give). What "
        "each benchmark measures: [benchmarks.md](benchmarks.md); the methods: [forecasting.md](forecasting.md).",
        inputs_table(files, pipeline, metrics, scenes),
    ]
    if kinds["main"]:
        sections.append(main_forecast_section(kinds["main"]))
    if kinds["main"] and kinds["steps"]:
        sections.append(steps_forecast_section(kinds["main"], kinds["steps"]))
    if kinds["main"] and kinds["variant"]:
        sections.append(variants_section(kinds["main"], kinds["variant"]))
    sections += [pipeline_section(p) for p in pipeline]
    sections += [scenes_section(rows) for rows in scenes]
    if metrics:
        sections.append(metrics_section(metrics))
    return "\n\n".join(sections) + "\n"


def write_page(path: str | os.PathLike, text: str) -> bool:
    """Write the page to `path` (whole file or nothing); True if it changed."""
    p = Path(path)
    if p.is_file() and read_text_file(p) == text:
        return False
    with atomic_path(p) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")
    return True


def page_matches(path: str | os.PathLike, text: str) -> bool:
    """Whether the file at `path` holds `text` already."""
    return read_text_file(path) == text


__all__ = ["BENCH_DIR", "command", "page_matches", "results_page", "write_page"]
