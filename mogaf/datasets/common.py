"""Shared input helpers for the dataset readers: strict JSON, typed fields,
options, time grids and PLY point clouds.

Every problem with an input file is raised as one `MogafError` line naming the
file (see mogaf.errors.input_error); no other exception type escapes these
helpers for any content of the file.
"""

from __future__ import annotations

import fnmatch
import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import MogafError, input_error

# Largest image side accepted from any JSON or image header. Checked before
# anything is allocated, so a corrupt size never triggers a huge allocation.
MAX_IMAGE_SIDE = 1 << 15
MAX_IMAGE_PIXELS = 1 << 28


# ---------------------------------------------------------------- JSON
def _reject_constant(name: str) -> Any:
    raise ValueError(f"non-finite number {name} is not valid JSON")


class _DuplicateKey(ValueError):
    """A JSON object names one key twice (json keeps the last silently)."""


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    obj: dict[str, Any] = {}
    for key, value in pairs:
        if key in obj:
            raise _DuplicateKey(key)
        obj[key] = value
    return obj


def load_json(path: str | os.PathLike, *, what: str = "file", expect: type = dict) -> Any:
    """Read a JSON file strictly: missing, unreadable, malformed, or an object
    that names a key twice -> one line."""
    p = Path(path)
    if not p.is_file():
        raise input_error(p, f"missing ({what})" if not p.exists() else f"is not a file ({what})")
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise input_error(p, f"cannot be read ({exc.strerror or exc.__class__.__name__})") from None
    try:
        obj = json.loads(raw, parse_constant=_reject_constant, object_pairs_hook=_unique_keys)
    except _DuplicateKey as exc:
        raise input_error(
            p, f"key {exc.args[0]!r} appears twice in one JSON object; which value is meant is ambiguous, keep one"
        ) from None
    except json.JSONDecodeError as exc:
        raise input_error(p, f"malformed JSON at line {exc.lineno} column {exc.colno}: {exc.msg}") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise input_error(p, f"malformed JSON: {exc}") from None
    except RecursionError:
        raise input_error(p, "malformed JSON: nested too deeply") from None
    if expect is not None and not isinstance(obj, expect):
        kind = {dict: "a JSON object", list: "a JSON array"}.get(expect, expect.__name__)
        raise input_error(p, f"must hold {kind}, got {_kind(obj)}")
    return obj


def _kind(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, (int, float)):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, list):
        return "an array"
    if isinstance(value, dict):
        return "an object"
    return type(value).__name__


def _short(value: Any, limit: int = 60) -> str:
    try:
        text = json.dumps(value)
    except (TypeError, ValueError, OverflowError, RecursionError):
        text = repr(type(value))
    return text if len(text) <= limit else text[: limit - 3] + "..."


def as_float(
    value: Any,
    path: str | os.PathLike,
    name: str,
    *,
    positive: bool = False,
    lo: float | None = None,
    hi: float | None = None,
) -> float:
    """A finite JSON number (not a boolean)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise input_error(path, f"{name} must be a number, got {_kind(value)} {_short(value)}")
    try:
        out = float(value)
    except OverflowError:
        raise input_error(path, f"{name} is too large ({_short(value)})") from None
    if not math.isfinite(out):
        raise input_error(path, f"{name} is not finite")
    if positive and out <= 0:
        raise input_error(path, f"{name} must be positive, got {out:g}")
    if lo is not None and out < lo:
        raise input_error(path, f"{name} must be >= {lo:g}, got {out:g}")
    if hi is not None and out > hi:
        raise input_error(path, f"{name} must be <= {hi:g}, got {out:g}")
    return out


def as_int(value: Any, path: str | os.PathLike, name: str, *, lo: int | None = None, hi: int | None = None) -> int:
    """A JSON integer (floats with an integral value are accepted)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise input_error(path, f"{name} must be an integer, got {_kind(value)} {_short(value)}")
    if isinstance(value, float):
        if not math.isfinite(value) or value != int(value):
            raise input_error(path, f"{name} must be an integer, got {value!r}")
        value = int(value)
    if lo is not None and value < lo:
        raise input_error(path, f"{name} must be >= {lo}, got {_short(value)}")
    if hi is not None and value > hi:
        raise input_error(path, f"{name} must be <= {hi}, got {_short(value)}")
    return int(value)


def as_image_side(value: Any, path: str | os.PathLike, name: str) -> int:
    """An image width or height from a JSON: positive and plausible."""
    return as_int(value, path, name, lo=1, hi=MAX_IMAGE_SIDE)


def as_array(value: Any, shape: tuple[int, ...], path: str | os.PathLike, name: str) -> np.ndarray:
    """A finite float64 array of exactly `shape` from nested JSON lists."""

    def check(v: Any, dims: tuple[int, ...]) -> None:
        if not dims:
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise input_error(path, f"{name} must hold numbers, found {_kind(v)}")
            return
        if not isinstance(v, list) or len(v) != dims[0]:
            got = f"{len(v)} entries" if isinstance(v, list) else _kind(v)
            want = f"a length-{shape[0]} list" if len(shape) == 1 else f"a {'x'.join(map(str, shape))} array"
            raise input_error(path, f"{name} must be {want} of numbers ({got} where {dims[0]} expected)")
        for item in v:
            check(item, dims[1:])

    check(value, shape)
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (OverflowError, ValueError, TypeError):
        raise input_error(path, f"{name} has numbers too large for float64") from None
    if not np.all(np.isfinite(arr)):
        raise input_error(path, f"{name} has non-finite values")
    return arr


def as_str(value: Any, path: str | os.PathLike, name: str) -> str:
    if not isinstance(value, str) or not value:
        raise input_error(path, f"{name} must be a non-empty string, got {_kind(value)} {_short(value)}")
    if "\x00" in value:
        raise input_error(path, f"{name} contains a NUL character")
    return value


def as_list(value: Any, path: str | os.PathLike, name: str) -> list:
    if not isinstance(value, list):
        raise input_error(path, f"{name} must be an array, got {_kind(value)}")
    return value


# ---------------------------------------------------------------- options
def option_int(
    options: Mapping, key: str, default: int, *, lo: int = 1, hi: int = 1 << 20, where: str = "dataset options"
) -> int:
    value = options.get(key, default) if options else default
    if value is None:
        value = default
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not (lo <= int(value) <= hi):
        raise MogafError(f"{where}: '{key}' must be an integer in [{lo}, {hi}], got {value!r}")
    return int(value)


def option_bool(options: Mapping, key: str, default: bool, *, where: str = "dataset options") -> bool:
    value = options.get(key, default) if options else default
    if value is None:
        return default
    if not isinstance(value, (bool, np.bool_)):
        raise MogafError(f"{where}: '{key}' must be true or false, got {value!r}")
    return bool(value)


def option_background(
    options: Mapping, default: Sequence[float] = (1.0, 1.0, 1.0), *, where: str = "dataset options"
) -> np.ndarray:
    value = options.get("background", default) if options else default
    if value is None:
        value = default
    try:
        arr = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise MogafError(f"{where}: 'background' must be three numbers in [0, 1], got {value!r}") from None
    if arr.shape != (3,) or not np.all(np.isfinite(arr)) or np.any(arr < 0) or np.any(arr > 1):
        raise MogafError(f"{where}: 'background' must be three numbers in [0, 1], got {value!r}")
    return arr


RIGIDITY_VALUES = {"rigid": 1, "nonrigid": 0, "non-rigid": 0, "unknown": -1}


def rigidity_rules(options: Mapping, *, where: str = "dataset options") -> list[tuple[str, int]]:
    """options['rigidity']: ordered mapping (or list of pairs) pattern -> rigid|nonrigid."""
    value = options.get("rigidity") if options else None
    if value is None:
        return []
    if isinstance(value, Mapping):
        items = list(value.items())
    elif isinstance(value, (list, tuple)):
        items = []
        for item in value:
            if isinstance(item, Mapping) and len(item) == 1:
                items.extend(item.items())
            elif isinstance(item, (list, tuple)) and len(item) == 2:
                items.append(tuple(item))
            else:
                raise MogafError(f"{where}: 'rigidity' entries must be pattern: rigid|nonrigid pairs, got {item!r}")
    else:
        raise MogafError(f"{where}: 'rigidity' must map name patterns to rigid|nonrigid, got {value!r}")
    rules = []
    for pattern, kind in items:
        if not isinstance(pattern, str) or not isinstance(kind, str) or kind.lower() not in RIGIDITY_VALUES:
            raise MogafError(f"{where}: 'rigidity' maps {pattern!r} to {kind!r}; expected rigid, nonrigid or unknown")
        rules.append((pattern, RIGIDITY_VALUES[kind.lower()]))
    return rules


def rigidity_of(name: str, rules: list[tuple[str, int]]) -> int:
    """First matching fnmatch pattern wins; unmatched names are unknown (-1)."""
    for pattern, flag in rules:
        if fnmatch.fnmatchcase(name, pattern):
            return flag
    return -1


# ---------------------------------------------------------------- warnings
class DatasetWarning(UserWarning):
    """The dataset is usable but probably not what its author meant (named file)."""


def warn_dataset(path: str | os.PathLike, problem: str) -> None:
    """The warning counterpart of `input_error`: `<file>: <what is odd>`."""
    import warnings

    warnings.warn(f"{os.fspath(path)}: {problem}", DatasetWarning, stacklevel=3)


# ---------------------------------------------------------------- time grid
def time_grid(
    times: np.ndarray, path: str | os.PathLike, num_timesteps: int | None = None, tol: float = 1e-3
) -> tuple[np.ndarray, int, float]:
    """Map normalised times in [0, 1] to indices of a uniform grid.

    Returns (time_index, num_timesteps, max_snap_error in grid steps).
    With `num_timesteps` given, times are snapped to that grid. Otherwise the
    grid has as many steps as there are distinct times when they lie on it;
    failing that, a grid whose step is the smallest gap between distinct times
    is tried (times missing from the grid are allowed). Else: one-line error.
    """
    t = np.asarray(times, dtype=np.float64)
    if t.size == 0:
        raise input_error(path, "no frame times")
    if not np.all(np.isfinite(t)) or np.any(t < 0) or np.any(t > 1):
        raise input_error(path, "frame times must be finite and lie in [0, 1]")

    def on_grid(T: int) -> tuple[np.ndarray, float]:
        scaled = t * (T - 1)
        idx = np.rint(scaled)
        return idx.astype(np.int64), float(np.max(np.abs(scaled - idx))) if t.size else 0.0

    if num_timesteps is not None:
        T = int(num_timesteps)
        idx, err = on_grid(T)
        return idx, T, err
    distinct = np.unique(t)
    if distinct.size == 1:
        return np.zeros(t.shape, np.int64), 1, 0.0
    T = int(distinct.size)
    idx, err = on_grid(T)
    if err <= tol:
        return idx, T, err
    gap = float(np.min(np.diff(distinct)))
    if gap > 0 and 1.0 / gap < 1e6:
        T2 = int(round(1.0 / gap)) + 1
        idx, err = on_grid(T2)
        if err <= tol:
            return idx, T2, err
    raise input_error(
        path,
        f"the {T} distinct frame times do not lie on a uniform grid; set the dataset option 'num_timesteps' to snap them to one",
    )
