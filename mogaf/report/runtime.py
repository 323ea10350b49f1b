"""Forecast error against the wall time that produced it; a Pareto line per method.

Each point is one (result, method): x = total wall time of the stages in the
method's lineage (ingest, priors, reconstruction, grouping, rigid init,
refinement, the method's forecast jobs; from Snakemake benchmark files), y =
the configured error metric on the forecast frames. Points come from the
default pipeline and the run-time sweep variants (quality-for-time knobs).
"""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path
from typing import Any

from ..artefact import atomic_path
from .metrics_files import load_metrics
from .table_format import Table
from .tables import METHOD_LABELS, METHOD_ORDER, METRICS, _metric, _variant, fmt

HIGHER_IS_BETTER = {
    "psnr",
    "ssim",
    "mpsnr",
    "mssim",
    "delta_3d@0.10",
    "delta_3d@0.05",
    "aj",
    "delta_avg",
    "occlusion_accuracy",
}


def collect_points(results: list[dict[str, Any]], metric: str, variants: list[str]) -> list[dict[str, Any]]:
    keep = {"default", *variants}
    points = []
    for r in results:
        if _variant(r) not in keep:
            continue
        for method in r.get("methods", {}):
            err = _metric(r, method, metric)
            wall = _metric(r, method, "total_wall_s")
            if err is None or wall is None or not (math.isfinite(err) and math.isfinite(wall)):
                continue
            points.append(
                {
                    "dataset": r["dataset"],
                    "scene": r["scene"],
                    "ratio": float(r["ratio"]),
                    "variant": _variant(r),
                    "method": method,
                    "wall_s": float(wall),
                    metric: float(err),
                }
            )
    return sorted(
        points,
        key=lambda p: (
            p["dataset"],
            p["scene"],
            p["ratio"],
            METHOD_ORDER.index(p["method"]) if p["method"] in METHOD_ORDER else 99,
            p["wall_s"],
        ),
    )


def pareto_front(points: list[dict[str, Any]], metric: str) -> list[dict[str, Any]]:
    """Points not beaten by a faster-or-equal point with a better-or-equal error."""
    better = (lambda a, b: a >= b) if metric in HIGHER_IS_BETTER else (lambda a, b: a <= b)
    front = []
    for p in sorted(points, key=lambda p: (p["wall_s"], -p[metric] if metric in HIGHER_IS_BETTER else p[metric])):
        if not front or not better(front[-1][metric], p[metric]):
            front.append(p)
    return front


def write_runtime_report(
    metrics_files: list[str], out_csv: str, out_md: str, out_png: str, params: dict[str, Any]
) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    metric = params.get("error_metric", "psnr")
    variants = list(params.get("runtime_variants", []))
    points = collect_points(load_metrics(metrics_files), metric, variants)
    label = METRICS.get(metric, (metric,))[0]

    table = Table(
        f"Forecast {label} against total wall time (default pipeline and run-time sweep)",
        ["dataset", "scene", "ratio", "variant", "method", "wall time [s]", label, "on Pareto line"],
    )
    scopes: dict[tuple[str, str, float], list[dict[str, Any]]] = defaultdict(list)
    for p in points:
        scopes[(p["dataset"], p["scene"], p["ratio"])].append(p)
    fronts = {}
    for scope, pts in scopes.items():
        for method in {p["method"] for p in pts}:
            fronts[scope + (method,)] = pareto_front([p for p in pts if p["method"] == method], metric)
    for p in points:
        on_front = any(q is p for q in fronts[(p["dataset"], p["scene"], p["ratio"], p["method"])])
        table.rows.append(
            [
                p["dataset"],
                p["scene"],
                f"{p['ratio']:g}",
                p["variant"],
                METHOD_LABELS.get(p["method"], p["method"]),
                f"{p['wall_s']:.1f}",
                fmt(p[metric], metric),
                "yes" if on_front else "no",
            ]
        )

    with atomic_path(out_csv) as tmp:
        Path(tmp).write_text(table.csv())
    with atomic_path(out_md) as tmp:
        Path(tmp).write_text(table.markdown())

    n = max(len(scopes), 1)
    fig, axes = plt.subplots(1, n, figsize=(5.5 * n, 4.2), squeeze=False)
    for ax, (scope, pts) in zip(axes[0], sorted(scopes.items())):
        for method in [m for m in METHOD_ORDER if any(p["method"] == m for p in pts)]:
            mine = [p for p in pts if p["method"] == method]
            line = ax.plot(
                [p["wall_s"] for p in fronts[scope + (method,)]],
                [p[metric] for p in fronts[scope + (method,)]],
                "-o",
                label=METHOD_LABELS.get(method, method),
                markersize=5,
            )[0]
            ax.scatter([p["wall_s"] for p in mine], [p[metric] for p in mine], color=line.get_color(), alpha=0.35, s=18)
        ax.set_title(f"{scope[0]}/{scope[1]}, ratio {scope[2]:g}")
        ax.set_xlabel("total wall time of the producing stages [s]")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    if not scopes:
        axes[0][0].text(0.5, 0.5, "no result", ha="center", va="center")
    fig.tight_layout()
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return [Path(out_csv), Path(out_md), Path(out_png)]
