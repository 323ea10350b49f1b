"""Per-scene comparison: one Markdown table per observation ratio, a row per
scene with every method's PSNR / LPIPS (and tracking EPE on scenes with
ground-truth tracks), the mean over the scenes, what
MoGaF's backtest chose per motion group and its coherence figures
(docs/results.md prints it for the metrics.json files it is given):

    python -m mogaf.report scenes results/mujoco/*/ratio0.6/metrics.json

Only methods that every scene of a ratio ran are compared: a mean over
different scenes would not compare.

A run's results can be kept beside the code as a scene-rows file (`--json`,
e.g. results/bench/scenes_family_cpu.json): its metrics.json records without
their per-view metrics, and a line saying where they were measured. The
measured-results page (docs/results.md) prints its tables from it:

    python -m mogaf.report scenes results/synthetic/f*/ratio*/metrics.json \
        --json results/bench/scenes_family_cpu.json --run "2-core ..., commit ..."

`--check FILE` instead says whether a rerun reproduces such a file: every
measured value the file keeps for a given result (image and tracking metrics
per method, grouping, reconstruction) must be repeated exactly; a method or
value the file does not keep is not compared.
"""

from __future__ import annotations

import json
import os
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from ..artefact import atomic_path
from ..config import leaves
from ..errors import MogafError, input_error
from .glance import _methods, best_text
from .metrics_files import METRIC_SECTIONS, checked_records, load_metrics, read_json, result_key
from .tables import _mean, _metric, _variant, budget_differences, fmt, forecast_record, method_label, steps_note


def _choice_text(info: dict[str, Any]) -> str:
    """A group's backtest decision: the candidate, with its weight when the
    candidates were blended (combine: weighted)."""
    choice = str(info.get("choice"))
    if isinstance(info.get("part_choices"), str):  # nonrigid_motion: rigid_parts, each part's own decision
        counts = Counter(c.replace("_", " ") for c in info["part_choices"].split())
        return "rigid parts (" + ", ".join(n + (f" x{k}" if k > 1 else "") for n, k in sorted(counts.items())) + ")"
    weight = info.get(f"backtest_weight_{choice}")
    return choice.replace("_", " ") + (f" {weight:.2f}" if isinstance(weight, float) and weight < 1.0 else "")


def _choices(result: dict[str, Any]) -> str:
    jobs = forecast_record(result, "mogaf").get("jobs") or {}
    infos = [info for info in jobs.values() if isinstance(info, dict)]
    if any(any(k.startswith("backtest_weight_") for k in info) for info in infos):
        return ", ".join(_choice_text(info) for info in infos) or "–"
    counts = Counter(_choice_text(info) for info in infos)
    return ", ".join(name + (f" x{n}" if n > 1 else "") for name, n in sorted(counts.items())) or "–"


def _coherence(result: dict[str, Any]) -> str:
    c = forecast_record(result, "mogaf").get("coherence") or {}
    rigid, still = c.get("rigid_distance_change"), c.get("still_displacement")
    return f"{fmt(rigid, 'coherence')} / {fmt(still, 'coherence')} ({c.get('still_gaussians', 0)})"


# Each cell: these metrics, and the tracking EPE where every scene of the ratio has it (synthetic scenes).
CELL_METRICS = ("psnr", "lpips")
CELL_NAMES = {"psnr": "PSNR", "lpips": "LPIPS", "epe_3d": "tracking EPE (m)"}


def _object_ious(result: dict[str, Any]) -> str:
    """The grouping's IoU with every ground-truth object (grouping_quality),
    then with each part of the objects made of several ("chest/lid"), or "–"."""
    grouping = result.get("grouping") or {}
    names, ious = grouping.get("object_names") or [], grouping.get("per_object_iou") or []
    names = list(names) + list(grouping.get("part_names") or [])
    ious = list(ious) + list(grouping.get("per_part_iou") or [])
    return ", ".join(f"{n} {float(v):.2f}" for n, v in zip(names, ious, strict=False)) or "–"


def recon_psnr(result: dict[str, Any]) -> float | None:
    """The reconstruction's PSNR at the held-out views of observed times (reconstruction_quality), or None."""
    value = ((result.get("reconstruction") or {}).get("heldout_observed") or {}).get("psnr")
    return None if value is None else float(value)


def recon_velocity(result: dict[str, Any]) -> tuple[float, float] | None:
    """The reconstruction's velocity error at the last observed step and the
    ground-truth points' mean speed (reconstruction_quality's observed_motion), or None."""
    motion = (result.get("reconstruction") or {}).get("observed_motion") or {}
    if "last_velocity_error" not in motion or "speed" not in motion:
        return None
    return float(motion["last_velocity_error"]), float(motion["speed"])


def still_points(result: dict[str, Any]) -> tuple[float, float] | None:
    """How far MoGaF's forecast moves the ground-truth points that never move
    (still_points_displacement) and the reconstruction's own jitter on them
    (observed_motion's still_jitter), or None where the scene has no such points."""
    moved = forecast_record(result, "mogaf").get("still_points_displacement")
    jitter = ((result.get("reconstruction") or {}).get("observed_motion") or {}).get("still_jitter")
    return None if moved is None or jitter is None else (float(moved), float(jitter))


def _pair_cell(pairs: list[tuple[float, float] | None]) -> str:
    """The mean of each side of the pairs that are there ("a / b"), or –."""
    there = [p for p in pairs if p is not None]
    if not there:
        return "–"
    return f"{np.mean([p[0] for p in there]):.4f} / {np.mean([p[1] for p in there]):.4f}"


def _cell(value: tuple[float | None, ...], best: tuple[str | None, ...], metrics: tuple[str, ...]) -> str:
    texts = [fmt(v, m) for v, m in zip(value, metrics, strict=True)]
    return " / ".join(f"**{t}**" if t == b else t for t, b in zip(texts, best, strict=True))


def _best(rows: list[dict[str, tuple[float | None, ...]]], metrics: tuple[str, ...]) -> list[tuple[str | None, ...]]:
    return [tuple(best_text([v[i] for v in row.values()], m) for i, m in enumerate(metrics)) for row in rows]


def cell_metrics(results: list[dict[str, Any]], methods: list[str]) -> tuple[str, ...]:
    """What the cells of one ratio's table give: PSNR / LPIPS, and the tracking
    EPE where every result has it for every method compared."""
    tracked = all(_metric(r, m, "epe_3d") is not None for r in results for m in methods)
    return CELL_METRICS + (("epe_3d",) if tracked else ())


# "Never worse than doing nothing": MoGaF's PSNR against the better of the two
# forecasts that learn nothing, per scene; a margin below -HARM_DB is harm.
NOTHING = ("frozen", "constant_velocity")
HARM_DB = 0.3


def psnr_margin(result: dict[str, Any]) -> float | None:
    """MoGaF's PSNR minus the better of frozen and constant velocity (dB), or None without them."""
    values = [_metric(result, m, "psnr") for m in ("mogaf", *NOTHING)]
    if any(v is None for v in values):
        return None
    return float(values[0]) - max(float(v) for v in values[1:])


def harm_note(results: list[dict[str, Any]]) -> str:
    """One line: on how many scenes MoGaF's margin is below -HARM_DB, and the worst."""
    margins = [(psnr_margin(r), r["scene"]) for r in results]
    margins = [(m, s) for m, s in margins if m is not None]
    if not margins:
        return ""
    worst, scene = min(margins)
    harmed = sum(m < -HARM_DB for m, _ in margins)
    return (
        f"MoGaF is more than {HARM_DB} dB PSNR below the better of frozen and constant velocity on "
        f"{harmed} of {len(margins)} scenes (worst margin {worst:+.2f} dB, {scene})"
    )


def ratio_table(results: list[dict[str, Any]]) -> str:
    """The table of results of one ratio under its caption (Markdown lines)."""
    methods = [m for m in _methods(results[0]) if all(m in r["methods"] for r in results)]
    if not methods:
        raise MogafError("no method was run on every scene of ratio " + str(results[0]["ratio"]))
    metrics = cell_metrics(results, methods)
    rows = [{m: tuple(_metric(r, m, k) for k in metrics) for m in methods} for r in results]
    means = {m: tuple(_mean([row[m][i] for row in rows]) for i in range(len(metrics))) for m in methods}
    mogaf = "mogaf" in methods
    margin = mogaf and all(m in methods for m in NOTHING)
    ious = any((r.get("grouping") or {}).get("per_object_iou") for r in results)
    recon = any(recon_psnr(r) is not None for r in results)
    velocity = any(recon_velocity(r) is not None for r in results)
    still = any(still_points(r) is not None for r in results)
    starred = {m: any(budget_differences(r, m) for r in results) for m in methods}
    header = ["scene"] + [method_label(results[0], m) + ("*" if starred[m] else "") for m in methods]
    header += ["MoGaF − best of frozen, const. velocity (dB)"] if margin else []
    header += ["grouping IoU per object"] if ious else []
    header += ["reconstruction PSNR, held-out views of observed times"] if recon else []
    header += ["reconstruction: GT points' velocity error at the last observed step / their speed"] if velocity else []
    header += ["GT points that never move: MoGaF moves them / the reconstruction's jitter (m)"] if still else []
    header += ["MoGaF's choice per group (weight)", "MoGaF coherence: rigid / still (m, still count)"] if mogaf else []
    datasets = ", ".join(sorted({r["dataset"] for r in results}))
    caption = f"Ratio {float(results[0]['ratio']):g} ({datasets}; {' / '.join(CELL_NAMES[k] for k in metrics)}):"
    lines = [caption, "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r, row, best in zip(results, rows, _best(rows, metrics)):
        variant = _variant(r)
        cells = [r["scene"] + ("" if variant == "default" else f" ({variant})")] + [
            _cell(row[m], best, metrics) for m in methods
        ]
        cells += [f"{psnr_margin(r):+.2f}"] if margin else []
        cells += [_object_ious(r)] if ious else []
        cells += [fmt(recon_psnr(r), "psnr")] if recon else []
        cells += [_pair_cell([recon_velocity(r)])] if velocity else []
        cells += [_pair_cell([still_points(r)])] if still else []
        cells += [_choices(r), _coherence(r)] if mogaf else []
        lines.append("| " + " | ".join(cells) + " |")
    (best,) = _best([means], metrics)
    cells = ["**mean**"] + [_cell(means[m], best, metrics) for m in methods]
    cells += [""] * (margin + ious)
    cells += [fmt(_mean([recon_psnr(r) for r in results]), "psnr")] if recon else []
    cells += [_pair_cell([recon_velocity(r) for r in results])] if velocity else []
    cells += [_pair_cell([still_points(r) for r in results])] if still else []
    cells += ["", ""] if mogaf else []
    lines.append("| " + " | ".join(cells) + " |")
    if margin:
        lines += ["", harm_note(results) + "."]
    if any(starred.values()):
        lines += ["", "\\* ran off its paper's settings; `metrics.json` records what each ran with."]
    note = steps_note(results, methods)
    if note:
        lines += ["", note + "."]
    return "\n".join(lines)


def scenes_table(results: list[dict[str, Any]]) -> str:
    """One table per ratio (PSNR / LPIPS at the held-out views and forecast
    times, and the tracking EPE where every scene has ground-truth tracks;
    best per row in bold), Markdown ending in a newline."""
    if not results:
        raise MogafError("scenes: no metrics.json given")
    out = []
    for ratio in sorted({float(r["ratio"]) for r in results}):
        of_ratio = sorted((r for r in results if float(r["ratio"]) == ratio), key=row_order)
        out += [ratio_table(of_ratio), ""]
    return "\n".join(out)


def row_order(result: dict[str, Any]) -> tuple[str, str, bool, str]:
    """A ratio's rows: by scene, then dataset, the default before its variants
    (a complete order, so the table does not depend on the files' order)."""
    variant = _variant(result)
    return (result["scene"], result["dataset"], variant != "default", variant)


def scenes(metrics_files: list[str | os.PathLike]) -> str:
    return scenes_table(load_metrics(metrics_files))


# ------------------------------------------------------------------ scene-rows files
SCENE_ROWS = "scenes"  # the key that makes a JSON file a scene-rows file


def scene_records(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The results as a scene-rows file keeps them, in table order: each
    metrics.json without its per-view metrics (the tables read the means) and
    without the path it was read from."""
    out = []
    for r in sorted(results, key=lambda r: (float(r["ratio"]), *row_order(r))):
        record = {k: v for k, v in r.items() if k != "_path"}
        record["methods"] = {
            m: {k: v for k, v in section.items() if k != "per_view"} for m, section in r["methods"].items()
        }
        out.append(record)
    return out


def write_scene_rows(path: str | os.PathLike, results: list[dict[str, Any]], run: str) -> None:
    """Write a scene-rows file (whole file or nothing): `run` says where and how
    the results were measured; a record per line, so a change diffs per scene."""
    problem = _run_problem(run)
    if problem:
        raise MogafError(f"scenes --json: --run {problem}")
    if Path(path).suffix != ".json":
        raise MogafError(f"scenes --json: {path} must end in .json (results/bench/ reads only .json files)")
    records = [json.dumps(r, sort_keys=True, allow_nan=False) for r in scene_records(results)]
    text = "{" + f'"run": {json.dumps(run)},\n"{SCENE_ROWS}": [\n' + ",\n".join(records) + "\n]}\n"
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")


def read_scene_rows(path: str | os.PathLike) -> tuple[str, list[dict[str, Any]]]:
    """(where they were measured, the checked records) of a scene-rows file."""
    doc = read_json(path)
    if not isinstance(doc, dict) or SCENE_ROWS not in doc:
        raise input_error(path, f"is not a scene-rows file (no '{SCENE_ROWS}' list)")
    problem = _run_problem(doc.get("run"))
    if problem:
        raise input_error(path, f"'run' {problem}")
    return doc["run"], checked_records(path, doc[SCENE_ROWS])


def _run_problem(run: Any) -> str | None:
    """What is wrong with a scene-rows file's run description (one line of text), or None."""
    if not isinstance(run, str) or not run.strip():
        return "must say where the results were measured"
    if "\n" in run or "\r" in run:
        return "must be one line (it is printed in a sentence of docs/results.md)"
    return None


# ------------------------------------------------------------------ reruns against a scene-rows file
# What a result measured: wall times, memory, provenance and per-view detail left out.
MEASURED_SECTIONS = ("grouping", "reconstruction")
MEASURED_METHOD_SECTIONS = tuple(s for s in METRIC_SECTIONS if s != "runtime")


def measured_values(result: dict[str, Any]) -> dict[str, Any]:
    """A result's measured values as {"section.key": value} (methods: "method.section.key")."""
    out: dict[str, Any] = {}
    parts = [((section,), result[section]) for section in MEASURED_SECTIONS if section in result]
    parts += [
        ((method, section), sections[section])
        for method, sections in result["methods"].items()
        for section in MEASURED_METHOD_SECTIONS
        if section in sections
    ]
    for prefix, node in parts:
        for keys, value in leaves(node, prefix):
            out[".".join(map(str, keys))] = value
    return out


def _differences(kept: dict[str, Any], rerun: dict[str, Any]) -> list[str]:
    """'name: kept -> rerun' for every measured value of `kept` that `rerun` does not repeat exactly."""
    a, b = measured_values(kept), measured_values(rerun)
    return [f"{k}: {a[k]!r} -> {b.get(k, 'missing')!r}" for k in a if k not in b or b[k] != a[k]]


def check_scene_rows(path: str | os.PathLike, results: list[dict[str, Any]]) -> tuple[list[str], bool]:
    """(report lines, whether every result equals its record in the scene-rows
    file `path`): a line per result that differs (its first differing values)
    or that the file does not hold, then a summary line."""
    _, records = read_scene_rows(path)
    kept = {result_key(r): r for r in records}
    lines, same = [], 0
    for r in sorted(results, key=lambda r: (float(r["ratio"]), *row_order(r))):
        key = result_key(r)
        name = f"{key[0]}/{key[1]} {key[2]:g} {key[3]}"
        if key not in kept:
            lines.append(f"{name}: not in {path}")
            continue
        diff = _differences(kept[key], r)
        if diff:
            more = f" (+{len(diff) - 3} more)" if len(diff) > 3 else ""
            lines.append(f"{name}: {len(diff)} values differ: {'; '.join(diff[:3])}{more}")
        else:
            same += 1
    lines.append(
        f"{path}: {same} of {len(results)} results identical"
        f" ({len(kept) - len(set(kept) & {result_key(r) for r in results})} of its {len(kept)} not given)"
    )
    return lines, same == len(results)
