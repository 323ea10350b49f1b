"""Results at a glance: a small Markdown table from metrics.json files.

One row per method (and result, when several files are given), the columns
PSNR / LPIPS / mPSNR / tracking EPE, the best of each result in bold. What was
not run is left out: a column no method has, a method with none of them.
`write_section` puts the table into a Markdown file between
`<!-- glance:start -->` and `<!-- glance:end -->` (the README's "Results at a
glance"):

    python -m mogaf.report glance results/synthetic/default/ratio0.6/metrics.json --write README.md
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from ..artefact import atomic_path
from ..errors import input_error
from ..paths import read_text_file
from .metrics_files import load_metrics
from .tables import METHOD_ORDER, _key, _metric, _variant, budget_differences, fmt, method_label

START, END = "<!-- glance:start -->", "<!-- glance:end -->"
# metric -> column header; fmt (mogaf.report.tables) gives the digits.
COLUMNS = {"psnr": "PSNR↑", "lpips": "LPIPS↓", "mpsnr": "mPSNR↑", "epe_3d": "tracking EPE (m)↓"}
LOWER_IS_BETTER = {"lpips", "epe_3d"}


def best_text(values: list[float | None], metric: str) -> str | None:
    """The best of `values` (None: not run) as the tables print it, or None."""
    present = [v for v in values if v is not None]
    if not present:
        return None
    return fmt(min(present) if metric in LOWER_IS_BETTER else max(present), metric)


def _methods(result: dict[str, Any]) -> list[str]:
    names = list(result["methods"])
    return [m for m in METHOD_ORDER if m in names] + sorted(m for m in names if m not in METHOD_ORDER)


def _result_label(result: dict[str, Any]) -> str:
    variant = _variant(result)
    return f"{result['dataset']}/{result['scene']} {float(result['ratio']):g}" + (
        "" if variant == "default" else f" ({variant})"
    )


def glance_table(results: list[dict[str, Any]]) -> str:
    """The table (Markdown, ending in a newline) of results read by load_metrics."""
    if not results:
        raise ValueError("glance_table needs at least one result")
    metrics = [x for x in COLUMNS if any(_metric(r, m, x) is not None for r in results for m in r["methods"])]
    several = len(results) > 1
    header = (["result"] if several else []) + ["method"] + [COLUMNS[x] for x in metrics]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    starred = False
    for r in sorted(results, key=lambda r: (_key(r), _variant(r))):
        methods = [m for m in _methods(r) if any(_metric(r, m, x) is not None for x in metrics)]
        best = {x: best_text([_metric(r, m, x) for m in methods], x) for x in metrics}
        for m in methods:
            star = bool(budget_differences(r, m))
            starred |= star
            cells = []
            for x in metrics:
                text = fmt(_metric(r, m, x), x)
                cells.append(f"**{text}**" if text == best.get(x) else text)
            lines.append(
                "| "
                + " | ".join(
                    ([_result_label(r)] if several else []) + [method_label(r, m) + ("*" if star else "")] + cells
                )
                + " |"
            )
    sources = ", ".join(f"`{r['_path']}`" for r in sorted(results, key=lambda r: r["_path"]))
    out = [f"From {sources}; best in bold.", ""] + lines
    if starred:
        out += ["", "Methods marked * ran off their papers' settings; `metrics.json` records what each ran with."]
    return "\n".join(out) + "\n"


def replace_section(
    text: str, block: str, where: str | os.PathLike = "text", markers: tuple[str, str] = (START, END)
) -> str:
    """`text` with what lies between the markers (default: the glance ones) replaced by `block`."""
    first, last = markers
    start = text.find(first)
    end = text.find(last, start + len(first)) if start >= 0 else -1
    if start < 0 or end < 0:
        raise input_error(where, f"has no '{first}' ... '{last}' section to write into")
    return text[: start + len(first)] + "\n" + block.rstrip("\n") + "\n" + text[end:]


def write_section(path: str | os.PathLike, block: str, markers: tuple[str, str] = (START, END)) -> bool:
    """Rewrite the marked section (default: the glance one) of the file at `path`; True if it changed."""
    p = Path(path)
    text = read_text_file(p)
    new = replace_section(text, block, p, markers)
    if new == text:
        return False
    with atomic_path(p) as tmp:
        Path(tmp).write_text(new, encoding="utf-8")
    return True


def section_matches(path: str | os.PathLike, block: str, markers: tuple[str, str] = (START, END)) -> bool:
    """Whether the marked section (default: the glance one) of the file at `path` holds `block` already."""
    p = Path(path)
    text = read_text_file(p)
    return replace_section(text, block, p, markers) == text


def glance(metrics_files: list[str | os.PathLike]) -> str:
    return glance_table(load_metrics(metrics_files))
