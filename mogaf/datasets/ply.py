"""Point clouds from PLY files (ASCII or binary little/big endian): the
positions, and the vertex colours where the file has them."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import input_error

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
MAX_PLY_HEADER = 1 << 16


def _read_ply_head(p: Path) -> tuple[bytes, int]:
    """The first MAX_PLY_HEADER bytes of the file and its size."""
    try:
        with open(p, "rb") as fh:
            head = fh.read(MAX_PLY_HEADER)
            size = os.fstat(fh.fileno()).st_size
    except OSError as exc:
        raise input_error(p, f"cannot be read ({exc.strerror or exc.__class__.__name__})") from None
    return head, size


def _ply_header_lines(p: Path, head: bytes) -> tuple[list[str], int]:
    """The header's lines (up to end_header) and the offset of the body."""
    if not head.startswith(b"ply"):
        raise input_error(p, "not a PLY file (no 'ply' magic)")
    end = head.find(b"end_header")
    if end < 0:
        raise input_error(p, "PLY header has no end_header line (or is longer than 64 KiB)")
    nl = head.find(b"\n", end)
    if nl < 0:
        raise input_error(p, "PLY header is truncated")
    try:
        lines = head[:end].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise input_error(p, "PLY header is not ASCII") from None
    return lines, nl + 1


def _ply_element(p: Path, parts: list[str]) -> dict[str, Any]:
    """An `element <name> <count>` line."""
    try:
        count = int(parts[2])
    except ValueError:
        raise input_error(p, f"PLY element '{parts[1]}' has a bad count {parts[2]!r}") from None
    if count < 0:
        raise input_error(p, f"PLY element '{parts[1]}' has a negative count")
    return {"name": parts[1], "count": count, "props": [], "has_list": False}


def _ply_property(p: Path, element: dict[str, Any], parts: list[str], line: str) -> None:
    """A `property` line, added to the element it follows."""
    if len(parts) >= 2 and parts[1] == "list":
        element["has_list"] = True
        element["props"].append(("__list__", None))
    elif len(parts) == 3 and parts[1] in _PLY_TYPES:
        if any(name == parts[2] for name, _ in element["props"]):
            raise input_error(p, f"PLY element '{element['name']}' lists property '{parts[2]}' twice")
        element["props"].append((parts[2], _PLY_TYPES[parts[1]]))
    else:
        raise input_error(p, f"PLY header has an unsupported property line {line.strip()!r}")


def _parse_ply_header(p: Path, lines: list[str]) -> tuple[str | None, list[dict[str, Any]]]:
    """(format, elements with their properties) of the header lines after 'ply'."""
    fmt = None
    elements: list[dict[str, Any]] = []
    for line in lines[1:]:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format" and len(parts) >= 2:
            fmt = parts[1]
        elif parts[0] == "element" and len(parts) == 3:
            elements.append(_ply_element(p, parts))
        elif parts[0] == "property" and elements:
            _ply_property(p, elements[-1], parts, line)
        elif parts[0] not in ("ply",):
            raise input_error(p, f"PLY header has an unexpected line {line.strip()!r}")
    return fmt, elements


def _ply_vertex(p: Path, fmt: str | None, elements: list[dict[str, Any]]) -> tuple[int, dict[str, Any], list[str]]:
    """(index of the vertex element, the element, its property names), checked."""
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise input_error(p, f"PLY format {fmt!r} is not supported (ascii or binary)")
    names = [e["name"] for e in elements]
    if "vertex" not in names:
        raise input_error(p, "PLY file has no vertex element")
    vi = names.index("vertex")
    vertex = elements[vi]
    if vertex["has_list"]:
        raise input_error(p, "PLY vertex element has list properties")
    props = [name for name, _ in vertex["props"]]
    for axis in ("x", "y", "z"):
        if axis not in props:
            raise input_error(p, f"PLY vertex element has no '{axis}' property")
    return vi, vertex, props


def _ply_ascii_columns(
    p: Path, elements: list[dict[str, Any]], vi: int, props: list[str], size: int, body_start: int
) -> dict[str, np.ndarray]:
    """The vertex columns of an ascii body, by property name."""
    n = elements[vi]["count"]
    if any(e["has_list"] for e in elements[:vi]):
        raise input_error(p, "PLY elements before 'vertex' have list properties (unsupported)")
    skip = sum(e["count"] for e in elements[:vi])
    # Every value is at least 2 bytes ("0 "): a header count larger than
    # the file allows is refused before reading.
    if (skip + n) * 2 > size:
        raise input_error(p, f"PLY header announces {n} vertices, more than the file holds")
    with open(p, "rb") as fh:
        fh.seek(body_start)
        text = fh.read().decode("ascii", errors="replace").splitlines()
    rows = [ln for ln in text if ln.strip()]
    if len(rows) < skip + n:
        raise input_error(p, f"PLY file is truncated: {len(rows) - skip} of {n} vertex lines")
    try:
        data = np.array([ln.split() for ln in rows[skip : skip + n]], dtype=np.float64)
    except ValueError:
        raise input_error(p, "PLY vertex lines are malformed (not numbers or wrong count)") from None
    if data.size == 0:
        data = data.reshape(0, len(props))
    if data.ndim != 2 or data.shape[1] != len(props):
        raise input_error(p, f"PLY vertex lines must have {len(props)} values each")
    return {name: data[:, i] for i, name in enumerate(props)}


def _ply_binary_columns(
    p: Path, fmt: str, elements: list[dict[str, Any]], vi: int, props: list[str], size: int, body_start: int
) -> dict[str, np.ndarray]:
    """The vertex columns of a binary body, by property name (float64)."""
    vertex = elements[vi]
    n = vertex["count"]
    order = "<" if fmt == "binary_little_endian" else ">"
    offset = body_start
    for e in elements[:vi]:
        if e["has_list"]:
            raise input_error(p, f"PLY element '{e['name']}' before 'vertex' has list properties (unsupported)")
        offset += e["count"] * sum(np.dtype(t).itemsize for _, t in e["props"])
    dtype = np.dtype([(name, order + t) for name, t in vertex["props"]])
    if offset + n * dtype.itemsize > size:
        raise input_error(p, f"PLY file is truncated: header announces {n} vertices of {dtype.itemsize} bytes")
    with open(p, "rb") as fh:
        fh.seek(offset)
        buf = fh.read(n * dtype.itemsize)
    rec = np.frombuffer(buf, dtype=dtype, count=n)
    return {name: rec[name].astype(np.float64) for name in props}


def _ply_colour(p: Path, cols: Mapping[str, np.ndarray], red_type: str) -> np.ndarray:
    """(P, 3) colours in [0, 1]: integer types scaled by their maximum, floats above 1 by 255."""
    rgb = np.stack([cols["red"], cols["green"], cols["blue"]], axis=1)
    kind = np.dtype(red_type).kind
    if kind in "ui":
        rgb = rgb / float(np.iinfo(np.dtype(red_type)).max)
    elif rgb.size and np.nanmax(rgb) > 1.0:
        rgb = rgb / 255.0
    if not np.all(np.isfinite(rgb)):
        raise input_error(p, "PLY vertex colours are not finite")
    return np.clip(rgb, 0.0, 1.0)


def read_ply_points(path: str | os.PathLike) -> tuple[np.ndarray, bool]:
    """Vertices of a PLY file as (P, 6) float32 xyz + rgb in [0, 1].

    Supports ascii, binary_little_endian and binary_big_endian files whose
    vertex element comes first or after elements without list properties.
    Returns (points, has_colour); without red/green/blue the colour is 0.5.
    """
    p = Path(path)
    head, size = _read_ply_head(p)
    lines, body_start = _ply_header_lines(p, head)
    fmt, elements = _parse_ply_header(p, lines)
    vi, vertex, props = _ply_vertex(p, fmt, elements)
    if fmt == "ascii":
        cols = _ply_ascii_columns(p, elements, vi, props, size, body_start)
    else:
        cols = _ply_binary_columns(p, fmt, elements, vi, props, size, body_start)
    dtypes = dict(vertex["props"])
    xyz = np.stack([cols["x"], cols["y"], cols["z"]], axis=1)
    if not np.all(np.isfinite(xyz)):
        raise input_error(p, "PLY vertices have non-finite coordinates")
    has_colour = all(c in cols for c in ("red", "green", "blue"))
    rgb = _ply_colour(p, cols, dtypes["red"]) if has_colour else np.full_like(xyz, 0.5)
    return np.concatenate([xyz, rgb], axis=1).astype(np.float32), has_colour
