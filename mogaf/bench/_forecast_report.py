"""Tables of `python -m mogaf.bench forecast`: the text table of a run and
the Markdown tables made from its --json files (--from-json, --summary).

A baseline shortened for a CPU run (--budget cpu, the settings in REDUCED)
is its own column, marked '*'; one trained for a step budget (--params
'{"ode": {"steps": 800}}') is its own column too, 'ode@800'. The same row in
two files must agree.
"""

from __future__ import annotations

import fnmatch
import json
import math
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mogaf.errors import MogafError
from mogaf.forecast.params import METHODS, TRAINED_METHODS

# Shortened training of the baselines for a CPU run (--budget cpu).
REDUCED: dict[str, dict[str, Any]] = {
    "gcn": {"epochs": 60},  # of 2001
    "ode": {"epochs": 2, "max_gaussians_per_epoch": 1024},  # of 40 epochs over all Gaussians
}
TORCH_METHODS = TRAINED_METHODS  # the methods that train a torch network


def format_table(rows: Sequence[Mapping[str, Any]], reduced: Mapping[str, Mapping[str, Any]] | None = None) -> str:
    """A text table; `reduced` maps shortened methods to the settings used."""
    reduced = reduced or {}
    head = f"{'set':<18} {'ratio':>5} {'method':<19} {'EPE':>9} {'rot(deg)':>9} {'train s':>8}  flags"
    lines = [head, "-" * len(head)]
    for r in rows:
        name = r["method"] + ("*" if r["method"] in reduced else "")
        lines.append(
            f"{r['set']:<18} {r['ratio']:>5.2f} {name:<19} {r['epe']:>9.4f} {r['rot_err_deg']:>9.2f} "
            f"{r['train_s']:>8.1f}  {','.join(r['flags'])}"
        )
    if reduced:
        lines.append("* shortened training (--budget cpu): " + "; ".join(f"{m}: {p}" for m, p in reduced.items()))
    return "\n".join(lines)


def set_selected(name: str, patterns: Sequence[str]) -> bool:
    """Whether a set's name matches one of --only's glob patterns."""
    return any(fnmatch.fnmatchcase(name, pat) for pat in patterns)


def column_name(header: Mapping[str, Any], method: str) -> str:
    """The table column of a method's rows in a file with this header: 'gcn*'
    for a --budget cpu baseline, 'ode@800' for one given a step budget
    (forecast.{gcn,ode}.steps), else the method's name."""
    col = method + ("*" if header.get("budget") == "cpu" and method in REDUCED else "")
    steps = ((header.get("params") or {}).get(method) or {}).get("steps") or 0
    return col + (f"@{int(steps)}" if method in REDUCED and int(steps) > 0 else "")


def method_of(column: str) -> str:
    """The method a column shows ('ode@800' -> 'ode', 'gcn*' -> 'gcn')."""
    return column.split("@")[0].rstrip("*")


def _column_order(columns: set[str]) -> list[str]:
    """Methods in METHODS order, each name before its shortened and its step-budget columns."""
    return sorted(columns, key=lambda c: (METHODS.index(method_of(c)) if method_of(c) in METHODS else 99, c))


# A --json file's "code": mogaf.bench.forecast.code_digest's 16 hex digits.
CODE_DIGEST = "[0-9a-f]{16}"


def read_rows(path: Path, only: Sequence[str] = ()) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """(header, rows) of a --json file written by this benchmark; with `only`
    (glob patterns), just the rows of the sets whose name matches one."""
    try:
        doc = json.loads(Path(path).read_text())
        rows = [dict(r) for r in doc["rows"]]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise MogafError(f"{path}: not a forecast benchmark file ({exc})") from None
    for i, r in enumerate(rows):
        missing = [k for k in ("set", "ratio", "method", "epe", "train_s") if k not in r]
        if missing:
            raise MogafError(f"{path}: row {i} has no {', '.join(missing)}")
        for key in ("ratio", "epe", "train_s"):  # NaN stands for a failed fit
            if not isinstance(r[key], (int, float)) or isinstance(r[key], bool):
                raise MogafError(f"{path}: row {i} has {key} {r[key]!r}, not a number")
    code = doc.get("code")
    if code is not None and not (isinstance(code, str) and re.fullmatch(CODE_DIGEST, code)):
        raise MogafError(f"{path}: has code {code!r}, not a digest of 16 hex digits (mogaf.bench.forecast.code_digest)")
    if only:
        rows = [r for r in rows if set_selected(str(r["set"]), only)]
    return {k: v for k, v in doc.items() if k != "rows"}, rows


def code_of(header: Mapping[str, Any]) -> str:
    """The code a file's rows were computed by (mogaf.bench.forecast.code_digest; '–': before digests)."""
    return header.get("code") or "–"


def code_note(headers: Mapping[str | Path, Mapping[str, Any]]) -> str:
    """A line naming each file's code (file -> its header, as read_rows gives
    it) where the files were not all computed by the same code, else ''."""
    codes = {Path(p).as_posix(): code_of(h) for p, h in headers.items()}
    if len(set(codes.values())) <= 1:
        return ""
    return "Rows computed by different code: " + ", ".join(f"`{p}` {c}" for p, c in codes.items())


def _same_number(a: float, b: float) -> bool:
    return a == b or (math.isnan(a) and math.isnan(b))


def comparison_table(paths: Sequence[str | Path], only: Sequence[str] = ()) -> str:
    """One Markdown table from several --json files: a line per (set, ratio),
    a future-EPE column per method (lowest in bold) and the training time of
    the learned methods. A baseline from a --budget cpu file is its own column,
    marked '*'. The same row in two files must agree."""
    cells: dict[tuple[str, float], dict[str, dict[str, Any]]] = {}
    origin: dict[tuple[str, float, str], str] = {}
    shapes: dict[tuple[str, float], tuple[Any, Any]] = {}
    columns: set[str] = set()
    headers: dict[str | Path, dict[str, Any]] = {}
    for path in paths:
        header, rows = read_rows(Path(path), only)
        headers[path] = header
        if header.get("budget") not in ("cpu", "paper"):
            raise MogafError(f"{path}: has no budget 'cpu' or 'paper' (written before budgets were recorded?)")
        for r in rows:
            key, col = (str(r["set"]), float(r["ratio"])), column_name(header, str(r["method"]))
            shape = (r.get("gaussians"), r.get("observed_frames"))
            if shapes.setdefault(key, shape) != shape:
                raise MogafError(
                    f"{path}: {key[0]} ratio {key[1]} was scored on other trajectories than in an earlier file"
                )
            old = cells.setdefault(key, {}).get(col)
            if old is not None and not _same_number(old["epe"], r["epe"]):
                raise MogafError(
                    f"{path}: {key[0]} ratio {key[1]} {col} has EPE {r['epe']:.6g}, "
                    f"{origin[(*key, col)]} has {old['epe']:.6g}"
                )
            cells[key][col] = r
            origin[(*key, col)] = str(path)
            columns.add(col)
    if not cells:
        raise MogafError("bench forecast: the --from-json files hold no rows")
    order = _column_order(columns)  # methods of other versions last
    timed = [c for c in order if method_of(c) in TORCH_METHODS]
    head = ["set", "ratio"] + [f"{c} EPE" for c in order] + [f"{c} train s" for c in timed]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for (name, ratio), row in cells.items():
        finite = [r["epe"] for r in row.values() if math.isfinite(r["epe"])]
        best = min(finite) if finite else None
        out = [name, f"{ratio:.2f}"]
        for c in order:
            r = row.get(c)
            if r is None:
                out.append("–")
                continue
            text = f"{r['epe']:.4f}" + (f" ({', '.join(r['flags'])})" if r.get("flags") else "")
            out.append(f"**{text}**" if r["epe"] == best else text)
        out += [f"{row[c]['train_s']:,.0f}" if c in row else "–" for c in timed]
        lines.append("| " + " | ".join(out) + " |")
    if any(c.endswith("*") for c in order):
        lines.append("")
        lines.append("\\* shortened training (--budget cpu): " + "; ".join(f"{m}: {REDUCED[m]}" for m in REDUCED))
    note = code_note(headers)
    if note:
        lines += ["", note]
    budgets = [c for c in order if "@" in c]
    if budgets:
        lines.append("")
        lines.append(
            "@N: trained for the fewest whole epochs that give each group at least N optimiser steps "
            "(forecast.{gcn,ode}.steps): " + ", ".join(budgets)
        )
    return "\n".join(lines)


def _cells(paths: Sequence[str | Path], only: Sequence[str] = ()) -> dict[tuple[str, float], dict[str, dict[str, Any]]]:
    """(set, ratio) -> column -> row, columns named as in comparison_table
    (column_name); the files are checked there."""
    cells: dict[tuple[str, float], dict[str, dict[str, Any]]] = {}
    for path in paths:
        header, rows = read_rows(Path(path), only)
        for r in rows:
            cells.setdefault((str(r["set"]), float(r["ratio"])), {})[column_name(header, str(r["method"]))] = r
    return cells


def summary_table(
    paths: Sequence[str | Path], against: Sequence[str] = ("constant_velocity", "frozen"), only: Sequence[str] = ()
) -> str:
    """Per method: the mean future EPE over the rows every method in the table
    has, and on how many of its rows it beats each reference in `against`."""
    comparison_table(paths, only)  # the same checks (agreeing files)
    cells = _cells(paths, only)
    columns = _column_order({c for row in cells.values() for c in row})
    shared = [k for k, row in cells.items() if all(c in row for c in columns)]
    head = ["method", f"mean EPE ({len(shared)} rows with every method)"] + [f"beats {a}" for a in against]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    means = {c: float(np.mean([cells[k][c]["epe"] for k in shared])) if shared else math.nan for c in columns}
    best = min((v for v in means.values() if math.isfinite(v)), default=None)
    for c in columns:
        out = [
            c,
            (f"**{means[c]:.4f}**" if means[c] == best else f"{means[c]:.4f}") if math.isfinite(means[c]) else "–",
        ]
        for a in against:
            both = [k for k, row in cells.items() if c in row and a in row]
            if c == a or not both:
                out.append("–")
                continue
            wins = sum(cells[k][c]["epe"] < cells[k][a]["epe"] for k in both)
            out.append(f"{wins} of {len(both)} ({100.0 * wins / len(both):.0f} %)")
        lines.append("| " + " | ".join(out) + " |")
    return "\n".join(lines)


def per_step_table(
    paths: Sequence[str | Path], fractions: Sequence[float] = (0.0, 0.5, 1.0), only: Sequence[str] = ()
) -> str:
    """Future EPE at the first, middle and last forecast step of every row and
    method that kept its per-step EPE: where a rollout goes wrong."""
    cells = _cells(paths, only)
    columns = _column_order({c for row in cells.values() for c, r in row.items() if r.get("epe_per_step")})
    head = ["set", "ratio", "steps"] + [f"{c} EPE at steps" for c in columns]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for (name, ratio), row in cells.items():
        n = max((len(r.get("epe_per_step") or []) for r in row.values()), default=0)
        if not n:
            continue
        picks = sorted({min(n - 1, int(round(f * (n - 1)))) for f in fractions})
        out = [name, f"{ratio:.2f}", " / ".join(str(i + 1) for i in picks)]
        for c in columns:
            steps = (row.get(c) or {}).get("epe_per_step") or []
            out.append(" / ".join(f"{steps[i]:.4f}" for i in picks) if len(steps) == n else "–")
        lines.append("| " + " | ".join(out) + " |")
    return "\n".join(lines)


def markdown_report(paths: Sequence[str | Path], only: Sequence[str] = ()) -> str:
    """What --from-json --summary prints: the comparison table, the summary
    (mean EPE, win counts) and the per-step EPE (docs/results.md shows it)."""
    return "\n\n".join(
        [comparison_table(paths, only), summary_table(paths, only=only), per_step_table(paths, only=only)]
    )
