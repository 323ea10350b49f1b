"""Paper-layout tables (Markdown, LaTeX, CSV, HTML) from metrics.json files.

Nothing is typed in by hand: every cell comes from a metrics.json. What was
not run is left out: a row, a column or a method with no result in any file
is not printed (a table with nothing left says so in one line), and a cell
missing among present ones shows a dash ("–"; empty in the CSV). Tables:
- forecast:  every result x method (image metrics, 3D EPE, run time)
- iphone:    paper Table 1 (iPhone layout: ratio x scene x method, mPSNR/mSSIM/mLPIPS)
- dnerf:     paper Table 2 (D-NeRF layout: ratio x scene x method, PSNR/SSIM/LPIPS)
- grouping:  Supp. grouping ablation (Gaga-4D vs ours)
- groupwise: Supp. group-wise ablation (encoder x Opt. x Forecast, tracking metrics)
- masking:   masking ablation (w/o masking vs ours)
"""

from __future__ import annotations

import math
import os
from collections import defaultdict
from pathlib import Path
from typing import Any

from ..artefact import atomic_path
from ..forecast.params import METHOD_LABELS, METHOD_ORDER, METHOD_TABLE, METHODS
from ..forecast.registry import defaults
from .metrics_files import load_metrics
from .table_format import MISSING, Table


def forecast_record(result: dict[str, Any], method: str) -> dict[str, Any]:
    """methods.<method>.forecast of a metrics.json ({} where the method or its record is absent)."""
    return (result.get("methods", {}).get(method) or {}).get("forecast") or {}


def method_label(result: dict[str, Any], method: str) -> str:
    """The method's label; MoGaF run in its paper mode (config/paper.yaml) is "MoGaF (paper)"."""
    params = forecast_record(result, method).get("params") or {}
    for row in METHOD_TABLE:  # a method run with the settings another row fixes is that row
        if row.section == method and row.fixed and all(params.get(k) == v for k, v in row.fixed.items()):
            return row.label
    return METHOD_LABELS.get(method, method)


# name -> (label, digits, scale); tracking fractions are shown in percent like the paper.
METRICS = {
    "psnr": ("PSNR↑", 2, 1.0),
    "ssim": ("SSIM↑", 4, 1.0),
    "lpips": ("LPIPS↓", 4, 1.0),
    "mpsnr": ("mPSNR↑", 2, 1.0),
    "mssim": ("mSSIM↑", 4, 1.0),
    "mlpips": ("mLPIPS↓", 4, 1.0),
    "epe_3d": ("EPE↓", 3, 1.0),
    "delta_3d@0.10": ("δ3D.10↑", 1, 100.0),
    "delta_3d@0.05": ("δ3D.05↑", 1, 100.0),
    "aj": ("AJ↑", 1, 100.0),
    "delta_avg": ("δavg↑", 1, 100.0),
    "occlusion_accuracy": ("OA↑", 1, 100.0),
    "total_wall_s": ("time [s]", 0, 1.0),
    "ari": ("ARI↑", 3, 1.0),
    "mean_iou": ("mIoU↑", 3, 1.0),
}
IMAGE_METRICS = ("psnr", "ssim", "lpips")
MASKED_METRICS = ("mpsnr", "mssim", "mlpips")
TRACKING_METRICS = ("epe_3d", "delta_3d@0.10", "delta_3d@0.05", "aj", "delta_avg", "occlusion_accuracy")
TABLE_NAMES = ("forecast", "iphone", "dnerf", "grouping", "groupwise", "masking")
TABLE_FORMATS = ("md", "tex", "csv", "html")


def fmt(value: Any, metric: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return MISSING
    _, digits, scale = METRICS.get(metric, (metric, 3, 1.0))
    return f"{float(value) * scale:.{digits}f}"


def _mean(values: list[float | None]) -> float | None:
    vals = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return sum(vals) / len(vals) if vals else None


AVERAGE_NOTE = (
    "Average: – where a method has no value for some scene of the row's ratio (its mean would be over other scenes)."
)


def _complete_mean(values: list[float | None]) -> float | None:
    """The mean of one method's values over a table's scenes, or None when a
    scene has none: an average over fewer scenes would not compare."""
    return None if any(v is None for v in values) else _mean(values)


def _metric(result: dict[str, Any], method: str, metric: str) -> float | None:
    m = result.get("methods", {}).get(method)
    if not m:
        return None
    for section in ("image", "tracking", "runtime"):
        sec = m.get(section) or {}
        if metric in sec:
            return sec[metric]
    return None


def _variant(result: dict[str, Any]) -> str:
    return result.get("variant") or "default"


def _key(result: dict[str, Any]) -> tuple[str, str, float]:
    return (result["dataset"], result["scene"], float(result["ratio"]))


def budget_differences(result: dict[str, Any], method: str) -> dict[str, tuple[Any, Any]]:
    """Forecaster parameters of this result that differ from the method's
    defaults (the papers' settings): {key: (used, default)}."""
    params = forecast_record(result, method).get("params")
    if not params:
        return {}
    if method not in METHODS:
        return {}
    ref = defaults(method)
    # the mode is in the label (method_label); the paper mode ignores the structured settings
    skip = {"num_threads", "mode"} | ({"structured"} if params.get("mode") == "paper" else set())
    return {k: (v, ref[k]) for k, v in sorted(params.items()) if k in ref and _differs(v, ref[k]) and k not in skip}


def _differs(used: Any, ref: Any) -> bool:
    """Whether a recorded setting is off its default; a nested mapping only by
    the keys it records (a setting added since a run does not mark it)."""
    if isinstance(used, dict) and isinstance(ref, dict):
        return any(k in ref and _differs(v, ref[k]) for k, v in used.items())
    return used != ref


def _results_label(results: list[dict[str, Any]], method: str) -> str:
    """The method's label in the first result that ran it (its plain label if none did)."""
    return next(
        (method_label(r, method) for r in results if method in r.get("methods", {})), METHOD_LABELS.get(method, method)
    )


def optimiser_steps(results: list[dict[str, Any]], method: str) -> tuple[int, int] | None:
    """Fewest and most optimiser steps one motion group of `method` trained for
    over these results (each forecast job's recorded `iterations`); None when
    the method records none (it trains nothing)."""
    steps = []
    for r in results:
        jobs = forecast_record(r, method).get("jobs") or {}
        for info in jobs.values():
            n = info.get("iterations") if isinstance(info, dict) else None
            if isinstance(n, (int, float)) and not isinstance(n, bool):
                steps.append(int(n))
    return (min(steps), max(steps)) if steps else None


def steps_note(results: list[dict[str, Any]], methods: list[str]) -> str | None:
    """'Optimiser steps per motion group: <method> <min>-<max>; ...' for the methods that train."""
    parts = []
    for m in methods:
        span = optimiser_steps(results, m)
        if span is not None:
            parts.append(f"{_results_label(results, m)} {span[0]:,}" + (f"-{span[1]:,}" if span[1] != span[0] else ""))
    return "Optimiser steps per motion group (recorded): " + "; ".join(parts) if parts else None


def _mark_budgets(t: Table, results: list[dict[str, Any]], methods: list[str]) -> dict[str, str]:
    """Method labels, with '*' (and a note) where a result ran a method off its defaults."""
    labels = {}
    for m in methods:
        diffs: dict[str, set[str]] = defaultdict(set)
        for r in results:
            for k, (used, ref) in budget_differences(r, m).items():
                diffs[f"{k} (default {ref})"].add(str(used))
        name = _results_label(results, m)
        labels[m] = name + ("*" if diffs else "")
        if diffs:
            t.notes.append(
                f"* {name}: run off its defaults: "
                + "; ".join(f"{k} = {', '.join(sorted(v))}" for k, v in sorted(diffs.items()))
            )
    note = steps_note(results, methods)
    if note:
        t.notes.append(note)
    return labels


# ------------------------------------------------------------------ tables
def forecast_table(results: list[dict[str, Any]]) -> Table:
    cols = ["dataset", "scene", "ratio", "variant", "method"] + [
        METRICS[m][0] for m in ("psnr", "ssim", "lpips", "mpsnr", "epe_3d", "total_wall_s")
    ]
    t = Table("Forecast results (every metrics.json, every method)", cols, keys=5)
    _mark_budgets(t, results, [m for m in METHOD_ORDER if any(m in r.get("methods", {}) for r in results)])
    for r in sorted(results, key=lambda r: (_key(r), _variant(r))):
        for method in [m for m in METHOD_ORDER if m in r.get("methods", {})]:
            label = method_label(r, method) + ("*" if budget_differences(r, method) else "")
            t.rows.append(
                [r["dataset"], r["scene"], f"{float(r['ratio']):g}", _variant(r), label]
                + [fmt(_metric(r, method, m), m) for m in ("psnr", "ssim", "lpips", "mpsnr", "epe_3d", "total_wall_s")]
            )
    return t.prune()


def _layout_table(results: list[dict[str, Any]], layout: str, metrics: tuple[str, ...], title: str) -> Table:
    chosen = [r for r in results if _variant(r) == "default" and r.get("protocol") == layout]
    methods = [m for m in METHOD_ORDER if any(m in r.get("methods", {}) for r in chosen)] or ["mogaf"]
    cols = ["Obs. ratio", "Scene"] + [METRICS[x][0] for _ in methods for x in metrics]
    t = Table(title, cols, keys=2)
    labels = _mark_budgets(t, chosen, methods)
    t.spans = [("", 2)] + [(labels[m], len(metrics)) for m in methods]
    by_ratio: dict[float, list[dict[str, Any]]] = defaultdict(list)
    for r in chosen:
        by_ratio[float(r["ratio"])].append(r)
    for ratio in sorted(by_ratio, reverse=True):
        group = sorted(by_ratio[ratio], key=_key)
        for r in group:
            t.rows.append(
                [f"{ratio:.0%}", f"{r['dataset']}/{r['scene']}"]
                + [fmt(_metric(r, m, x), x) for m in methods for x in metrics]
            )
        if len(group) > 1:
            values = [[_metric(r, m, x) for r in group] for m in methods for x in metrics]
            cells = [_complete_mean(v) for v in values]
            t.rows.append([f"{ratio:.0%}", "Average"] + [fmt(v, x) for v, x in zip(cells, metrics * len(methods))])
            # said where a dash stands beside values (a column of no value at all is pruned)
            partial = any(None in v and any(x is not None for x in v) for v in values)
            if partial and AVERAGE_NOTE not in t.notes:
                t.notes.append(AVERAGE_NOTE)
    t.notes.append(
        "GSPred's original 4D-GS-based column of the paper is not reproduced here (it needs the 4D-GS deformation field); its forecaster runs on our representation as GSPred-SoM."
    )
    t.prune()
    # a method whose every column went (no result) takes its '*' note with it
    shown = {label.removesuffix("*") for label, _ in t.spans or []}
    t.notes = [n for n in t.notes if not n.startswith("* ") or n[2:].split(": run off its defaults")[0] in shown]
    return t


def iphone_table(results: list[dict[str, Any]]) -> Table:
    return _layout_table(
        results, "iphone", MASKED_METRICS, "Forecasting on iPhone-layout scenes (paper Table 1 layout)"
    )


def dnerf_table(results: list[dict[str, Any]]) -> Table:
    return _layout_table(results, "dnerf", IMAGE_METRICS, "Forecasting on D-NeRF-layout scenes (paper Table 2 layout)")


def _pairs(results: list[dict[str, Any]], variant: str) -> list[tuple[dict[str, Any], dict[str, Any]]]:
    """(default result, variant result) for every scope that has both."""
    default = {_key(r): r for r in results if _variant(r) == "default"}
    return [(default[_key(r)], r) for r in results if _variant(r) == variant and _key(r) in default]


def _image_metric_names(result: dict[str, Any]) -> tuple[str, ...]:
    return MASKED_METRICS if result.get("protocol") == "iphone" else IMAGE_METRICS


def grouping_table(results: list[dict[str, Any]], ablations: dict[str, Any]) -> Table:
    names = ("psnr", "ssim", "lpips", "delta_3d@0.10", "delta_3d@0.05", "occlusion_accuracy", "ari", "mean_iou")
    cols = ["scope", "Method"] + [("(m)" + METRICS[n][0]) if n in IMAGE_METRICS else METRICS[n][0] for n in names]
    t = Table("Grouping ablation: Gaga-4D vs motion-aware grouping (Supp. Table, MoGaF forecaster)", cols, keys=2)
    variants = [v for v, spec in ablations.get("variants", {}).items() if (spec.get("labels") or {}).get("grouping")]
    for variant in variants:
        pairs = _pairs(results, variant)
        scopes: dict[tuple[str, float], list[tuple[dict[str, Any], dict[str, Any]]]] = defaultdict(list)
        for d, v in pairs:
            scopes[(d["dataset"], float(d["ratio"]))].append((d, v))
        for (dataset, ratio), items in sorted(scopes.items()):
            scope = f"{dataset} {ratio:.0%} ({len(items)} scene{'s' if len(items) > 1 else ''})"
            label = ablations["variants"][variant]["labels"]["grouping"]
            for row_label, pick in ((label, 1), ("Ours", 0)):
                cells = []
                for n in names:
                    if n in ("ari", "mean_iou"):
                        vals = [(item[pick].get("grouping") or {}).get(n) for item in items]
                    else:
                        # Masked image metrics where the layout has them (iPhone), as the paper.
                        metric = {"psnr": 0, "ssim": 1, "lpips": 2}.get(n)
                        vals = [
                            _metric(
                                item[pick],
                                "mogaf",
                                _image_metric_names(item[pick])[metric] if metric is not None else n,
                            )
                            for item in items
                        ]
                    cells.append(fmt(_mean(vals), n))
                t.rows.append([scope, row_label] + cells)
    t.notes.append("Image metrics are masked (mPSNR, mSSIM, mLPIPS) for iPhone-layout scenes, as in the paper.")
    return t.prune()


def groupwise_table(results: list[dict[str, Any]], ablations: dict[str, Any]) -> Table:
    cols = ["Encoder", "Opt.", "Forecast"] + [METRICS[m][0] for m in TRACKING_METRICS]
    t = Table(
        "Group-wise design ablation (Supp. Table: encoder x group-wise optimisation x group-wise forecasting)",
        cols,
        keys=3,
    )
    specs = [
        (v, s["labels"])
        for v, s in ablations.get("variants", {}).items()
        if {"encoder", "opt", "forecast"} <= set(s.get("labels") or {})
    ]
    for encoder in ("HC", "LW"):
        for variant, labels in sorted(
            (x for x in specs if x[1]["encoder"] == encoder), key=lambda x: (x[1]["forecast"], x[1]["opt"])
        ):
            chosen = [r for r in results if _variant(r) == variant]
            mark = lambda b: "✓" if b else "–"  # noqa: E731
            t.rows.append(
                [f"{encoder} ({len(chosen)} results)", mark(labels["opt"]), mark(labels["forecast"])]
                + [fmt(_mean([_metric(r, "mogaf", m) for r in chosen]), m) for m in TRACKING_METRICS]
            )
    return t.prune()


def masking_table(results: list[dict[str, Any]], ablations: dict[str, Any]) -> Table:
    cols = ["scope", "Method"] + [METRICS[m][0] for m in IMAGE_METRICS]
    t = Table("Masking ablation: forecaster trained with and without contiguous-span masking", cols, keys=2)
    variants = [v for v, s in ablations.get("variants", {}).items() if (s.get("labels") or {}).get("masking") is False]
    for variant in variants:
        scopes: dict[tuple[str, float], list[tuple[dict[str, Any], dict[str, Any]]]] = defaultdict(list)
        for d, v in _pairs(results, variant):
            scopes[(d["dataset"], float(d["ratio"]))].append((d, v))
        for (dataset, ratio), items in sorted(scopes.items()):
            scope = f"{dataset} {ratio:.0%} ({len(items)} scene{'s' if len(items) > 1 else ''})"
            for label, pick in (("Ours w/o masking", 1), ("Ours", 0)):
                t.rows.append(
                    [scope, label]
                    + [fmt(_mean([_metric(item[pick], "mogaf", m) for item in items]), m) for m in IMAGE_METRICS]
                )
    return t.prune()


def build_tables(results: list[dict[str, Any]], ablations: dict[str, Any]) -> dict[str, Table]:
    return {
        "forecast": forecast_table(results),
        "iphone": iphone_table(results),
        "dnerf": dnerf_table(results),
        "grouping": grouping_table(results, ablations),
        "groupwise": groupwise_table(results, ablations),
        "masking": masking_table(results, ablations),
    }


def write_tables(
    metrics_files: list[str], out_files: list[str], params: dict[str, Any], ablations: dict[str, Any]
) -> list[Path]:
    """Write table_<name>.{md,tex,csv,html} for every table; out_files name them all."""
    tables = build_tables(load_metrics(metrics_files), ablations)
    written = []
    for path in out_files:
        p = Path(path)
        name, ext = p.stem.removeprefix("table_"), p.suffix.lstrip(".")
        if name not in tables or ext not in TABLE_FORMATS:
            raise ValueError(f"unexpected table output {path}")
        table = tables[name]
        text = {"md": table.markdown, "tex": table.latex, "csv": table.csv, "html": table.html}[ext]()
        with atomic_path(p) as tmp:
            Path(tmp).write_text(text)
        written.append(p)
    return written


def main_table_paths(out_dir: str | os.PathLike) -> list[str]:
    return [str(Path(out_dir, f"table_{n}.{e}")) for n in TABLE_NAMES for e in TABLE_FORMATS]
