"""Reading metrics.json files for the reports: each one checked, one line naming
the file and the key for a bad one, duplicates of one result refused (load_metrics)."""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path
from typing import Any

from ..errors import input_error

NO_RESULT = "no result"
# Sections of methods.<m> whose every value is a metric: a number or null.
METRIC_SECTIONS = ("image", "tracking", "runtime")


def _no_constants(name: str) -> Any:
    raise ValueError(f"{name} is not a JSON number (evaluate never writes it)")


# The values a metric can take (inclusive); a metric not listed here only
# has to be finite (PSNR, EPE-free counts).
_RANGES = (
    ("ssim", (-1.0, 1.0)),
    ("mssim", (-1.0, 1.0)),
    ("lpips", (0.0, math.inf)),
    ("mlpips", (0.0, math.inf)),
    ("epe", (0.0, math.inf)),
    ("delta_", (0.0, 1.0)),
    ("aj", (0.0, 1.0)),
    ("occlusion_accuracy", (0.0, 1.0)),
    ("ari", (-1.0, 1.0)),
    ("mean_iou", (0.0, 1.0)),
)


def _out_of_range(section: str, name: str, value: float) -> str | None:
    """Why a finite metric value is impossible, or None."""
    if section == "runtime":
        lo, hi = 0.0, math.inf
    else:
        lo, hi = next((r for prefix, r in _RANGES if name == prefix or name.startswith(prefix)), (-math.inf, math.inf))
    if lo <= value <= hi:
        return None
    return f"is {value!r}, outside the range [{lo:g}, {hi:g}] of {name}"


def _folder_ratio(path: Path) -> float | None:
    """The observation ratio a results folder names (`ratio0.6`), if any."""
    for part in reversed(path.parts[:-1]):
        match = re.fullmatch(r"ratio(\d+(?:\.\d+)?|\.\d+)", part)
        if match:
            return float(match.group(1))
    return None


def is_number(value: Any) -> bool:
    """A finite int or float (not a bool)."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:  # an integer beyond float range
        return False


def _header_problem(data: dict[str, Any]) -> str | None:
    """What is wrong with the result's dataset, scene, ratio, variant or protocol, or None."""
    for key in ("dataset", "scene"):
        if not isinstance(data.get(key), str) or not data[key]:
            return f"'{key}' must be a non-empty string, got {data.get(key)!r}"
    ratio = data.get("ratio")
    if not is_number(ratio) or not 0 < ratio < 1:
        return f"'ratio' must be a number in (0, 1), got {ratio!r}"
    for key in ("variant", "protocol"):
        if data.get(key) is not None and not isinstance(data[key], str):
            return f"'{key}' must be a string, got {data[key]!r}"
    return None


def _value_problem(where: str, section: str, name: str, value: Any) -> str | None:
    """What is wrong with one metric value (a number in its range, or null) at `where`, or None."""
    if value is not None and not is_number(value):
        return f"'{where}' must be a number or null, got {value!r}"
    why = None if value is None else _out_of_range(section, name, value)
    if why:
        return f"'{where}' {why}"
    return None


def _method_problem(method: str, section: Any) -> str | None:
    """What is wrong with methods.<method>, or None."""
    if not isinstance(section, dict):
        return f"'methods.{method}' must be an object"
    forecast = section.get("forecast")
    if forecast is not None and not isinstance(forecast, dict):
        return f"'methods.{method}.forecast' must be an object"
    for key in ("params", "jobs"):
        if forecast is not None and not isinstance(forecast.get(key) or {}, dict):
            return f"'methods.{method}.forecast.{key}' must be an object"
    for part in METRIC_SECTIONS:
        values = section.get(part)
        if values is None:
            continue
        if not isinstance(values, dict):
            return f"'methods.{method}.{part}' must be an object"
        for name, value in values.items():
            problem = _value_problem(f"methods.{method}.{part}.{name}", part, name, value)
            if problem:
                return problem
    return None


def _grouping_problem(grouping: Any) -> str | None:
    """What is wrong with the 'grouping' section, or None."""
    if grouping is not None and not isinstance(grouping, dict):
        return "'grouping' must be an object"
    for name in ("ari", "mean_iou"):
        problem = _value_problem(f"grouping.{name}", "grouping", name, (grouping or {}).get(name))
        if problem:
            return problem
    for name in ("per_object_iou", "per_part_iou"):
        values = (grouping or {}).get(name)
        if values is None:
            continue
        if not isinstance(values, list):
            return f"'grouping.{name}' must be a list"
        for i, value in enumerate(values):
            problem = _value_problem(f"grouping.{name}[{i}]", "grouping", "mean_iou", value)
            if problem or value is None:
                return problem or f"'grouping.{name}[{i}]' must be a number, got null"
    for name in ("object_names", "part_names"):
        values = (grouping or {}).get(name)
        if values is not None and not (isinstance(values, list) and all(isinstance(v, str) for v in values)):
            return f"'grouping.{name}' must be a list of names"
    return None


# The figures of the reconstruction's observed motion and of a forecast's coherence the tables read.
MOTION_FIGURES = ("last_velocity_error", "speed", "still_jitter")
COHERENCE = ("rigid_distance_change", "still_displacement")


def _numbers_problem(where: str, section: Any, names: tuple[str, ...]) -> str | None:
    """What is wrong with an optional object whose `names` are numbers or null, or None."""
    if section is None:
        return None
    if not isinstance(section, dict):
        return f"'{where}' must be an object"
    for name in names:
        value = section.get(name)
        if value is not None and not is_number(value):
            return f"'{where}.{name}' must be a number or null, got {value!r}"
    return None


def _reconstruction_problem(data: dict[str, Any]) -> str | None:
    """What is wrong with the reconstruction figures and MoGaF's coherence
    figures the per-scene table reads (mogaf.report.scenes), or None."""
    recon = data.get("reconstruction")
    if recon is not None and not isinstance(recon, dict):
        return "'reconstruction' must be an object"
    for part, names in (("heldout_observed", ("psnr",)), ("observed_motion", MOTION_FIGURES)):
        problem = _numbers_problem(f"reconstruction.{part}", (recon or {}).get(part), names)
        if problem:
            return problem
    for method, section in data["methods"].items():
        forecast = section.get("forecast") or {}
        problem = _numbers_problem(f"methods.{method}.forecast.coherence", forecast.get("coherence"), COHERENCE)
        problem = problem or _numbers_problem(f"methods.{method}.forecast", forecast, ("still_points_displacement",))
        if problem:
            return problem
    return None


def _metrics_problem(data: dict[str, Any]) -> str | None:
    """What makes a parsed metrics.json unusable for the tables, or None."""
    problem = _header_problem(data)
    if problem:
        return problem
    if not isinstance(data["methods"], dict):
        return "'methods' must be an object"
    for method, section in data["methods"].items():
        problem = _method_problem(method, section)
        if problem:
            return problem
    return _grouping_problem(data.get("grouping")) or _reconstruction_problem(data)


def result_key(data: dict[str, Any]) -> tuple[str, str, float, str]:
    """(dataset, scene, ratio, variant): what one metrics.json is the result of."""
    return (data["dataset"], data["scene"], float(data["ratio"]), data.get("variant") or "default")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"{text} is beyond the range of a float (evaluate never writes it)")
    return value


def read_json(path: str | os.PathLike) -> Any:
    """A JSON file as evaluate writes it (no NaN, Infinity or number beyond a
    float's range); one line naming the file otherwise."""
    p = Path(path)
    try:
        return json.loads(p.read_bytes(), parse_constant=_no_constants, parse_float=_finite_float)
    except (OSError, ValueError, RecursionError) as exc:  # ValueError: also malformed UTF-8, NaN, Infinity
        raise input_error(
            p, f"not readable JSON ({exc.__class__.__name__}: {str(exc).splitlines()[0] if str(exc) else ''})"
        ) from None


def checked_records(path: str | os.PathLike, records: Any) -> list[dict[str, Any]]:
    """The metrics.json records kept in one file (a scene-rows file,
    mogaf.report.scenes), each checked as load_metrics checks a metrics.json:
    one line naming the file and the record for a bad one or a repeated result."""
    if not isinstance(records, list) or not records:
        raise input_error(path, "'scenes' must be a non-empty list of metrics.json records")
    seen: dict[tuple[str, str, float, str], int] = {}
    out = []
    for i, data in enumerate(records):
        if not isinstance(data, dict) or "methods" not in data:
            raise input_error(path, f"scenes[{i}] is not a metrics.json record (no 'methods' section)")
        problem = _metrics_problem(data)
        if problem:
            raise input_error(path, f"scenes[{i}]: {problem}")
        key = result_key(data)
        if key in seen:
            raise input_error(path, f"scenes[{i}] holds the same result as scenes[{seen[key]}]")
        seen[key] = i
        out.append({**data, "_path": f"{Path(path).as_posix()}#scenes[{i}]"})
    return out


def load_metrics(paths: list[str | os.PathLike]) -> list[dict[str, Any]]:
    """Read metrics.json files; a malformed one, or two files of one result
    (one row each in every table), fail with one line naming the file."""
    out = []
    seen: dict[tuple[str, str, float, str], str] = {}
    for path in sorted({str(p) for p in paths}):
        p = Path(path)
        if not p.is_file():
            raise input_error(p, "no such metrics file")
        data = read_json(p)
        if not isinstance(data, dict) or "methods" not in data:
            raise input_error(p, "not a mogaf metrics.json (no 'methods' section)")
        problem = _metrics_problem(data)
        if problem:
            raise input_error(p, f"not a usable metrics.json: {problem}")
        folder_ratio = _folder_ratio(p.resolve())
        if folder_ratio is not None and not math.isclose(folder_ratio, float(data["ratio"]), abs_tol=1e-9):
            raise input_error(
                p,
                f"says ratio {data['ratio']:g}, but lies in a folder of ratio {folder_ratio:g}; "
                "a metrics.json moved or edited by hand, rerun evaluate",
            )
        key = result_key(data)
        if key in seen:
            raise input_error(
                p,
                f"holds the same result as {seen[key]} ({key[0]}/{key[1]}, ratio {key[2]:g}, "
                f"variant {key[3]}); the tables take one file per result, remove one",
            )
        seen[key] = str(p)
        data["_path"] = str(p)
        out.append(data)
    return out
