"""Artefact header: the format version and attr names, the config digest,
attr values encoded for HDF5 and decoded back, and opening an artefact with
its header (format, stage, package version, config digest) checked."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from .. import __version__
from ..errors import MogafError, input_error

# 2: every dataset carries a checksum (Fletcher-32, or ATTR_CHECKSUM where
# HDF5 cannot filter it); version-1 files have none and are refused.
FORMAT_VERSION = 2

ATTR_FORMAT = "mogaf_format_version"
ATTR_STAGE = "mogaf_stage"
ATTR_DIGEST = "mogaf_config_digest"
ATTR_PACKAGE = "mogaf_package_version"
ATTR_CREATED = "mogaf_created_utc"
# Lineage: a digest of the artefact's config digest and its inputs' lineage
# digests, and those inputs' lineage digests by stage (see `stage_inputs`).
ATTR_LINEAGE = "mogaf_lineage_digest"
ATTR_INPUTS = "mogaf_input_digests"
# On a dataset HDF5 cannot filter (a scalar, an empty array, variable-length
# strings): a digest of its dtype, shape and values, checked on every open.
ATTR_CHECKSUM = "mogaf_checksum"
RESERVED_ATTRS = (ATTR_FORMAT, ATTR_STAGE, ATTR_DIGEST, ATTR_PACKAGE, ATTR_CREATED, ATTR_LINEAGE, ATTR_INPUTS)


# ---------------------------------------------------------------- digests
def _canonical(obj: Any) -> Any:
    """JSON-able canonical form: sorted mappings, lists for tuples/arrays."""
    if isinstance(obj, Mapping):
        return {str(k): _canonical(v) for k, v in sorted(obj.items(), key=lambda kv: str(kv[0]))}
    if isinstance(obj, (list, tuple)):
        return [_canonical(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _canonical(obj.tolist())
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        # repr round-trips floats exactly; avoids 0.1 vs 0.1000000001 drift.
        return repr(float(obj))
    if isinstance(obj, Path):
        return str(obj)
    return obj


def config_digest(params: Any) -> str:
    """Stable short digest of the parameters that determine an artefact."""
    text = json.dumps(_canonical(params), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def dataset_checksum(arr: np.ndarray) -> str:
    """Digest of an array's dtype, shape and values (strings as UTF-8)."""
    h = hashlib.blake2b(digest_size=16)
    if arr.dtype.kind in "USO":
        items = [v.decode() if isinstance(v, bytes) else str(v) for v in np.asarray(arr).reshape(-1).tolist()]
        h.update(f"str\0{arr.shape}\0".encode())
        for item in items:
            data = item.encode()
            h.update(len(data).to_bytes(8, "little") + data)
    else:
        h.update(f"{arr.dtype.str}\0{arr.shape}\0".encode())
        h.update(np.ascontiguousarray(arr).tobytes())
    return h.hexdigest()


# ---------------------------------------------------------------- attr values
def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"attribute value of type {type(obj).__name__} is not JSON-serialisable")


def _attr_value(value: Any) -> Any:
    if isinstance(value, (Mapping, list, tuple)) and not isinstance(value, np.ndarray):
        # Structured attrs are stored as JSON text (numbers stay numbers).
        try:
            return "json:" + json.dumps(value, sort_keys=True, default=_json_default, allow_nan=False)
        except ValueError:
            raise MogafError("refusing to write a non-finite number inside a structured attribute") from None
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (float, np.floating)) and not np.isfinite(value):
        raise MogafError(f"refusing to write non-finite attribute value {value!r}")
    return value


def _decode_attr(value: Any) -> Any:
    if isinstance(value, bytes):
        value = value.decode()
    if isinstance(value, str) and value.startswith("json:"):
        return json.loads(value[5:])
    if isinstance(value, np.generic):
        return value.item()
    return value


def _compatible_package(version: str) -> bool:
    """Same major version (same minor while the package is 0.x)."""
    try:
        theirs = [int(x) for x in str(version).split(".")[:2]]
        ours = [int(x) for x in __version__.split(".")[:2]]
    except ValueError:
        return False
    return theirs[0] == ours[0] and (ours[0] != 0 or theirs[1] == ours[1])


def _check_header(fh: h5py.File, path: Path, stages: tuple[str, ...] | None, expected_digest: str | None) -> None:
    if ATTR_FORMAT not in fh.attrs:
        raise input_error(path, "not a MoGaF artefact (no format version attribute)")
    version = _decode_attr(fh.attrs[ATTR_FORMAT])
    if isinstance(version, bool) or not isinstance(version, int):
        # e.g. "1" written by another tool: not this format, however it prints
        raise input_error(
            path,
            f"format version {version!r} is a {type(version).__name__}, not an integer; "
            "not an artefact this mogaf wrote, rerun the stage that writes it",
        )
    if version != FORMAT_VERSION:
        raise input_error(
            path, f"format version {version}, this mogaf reads version {FORMAT_VERSION}; rerun the stage that wrote it"
        )
    for name, value in fh.attrs.items():  # a structured attr a reader would fail to decode later, far from here
        if isinstance(value, bytes):
            value = value.decode(errors="replace")
        if isinstance(value, str) and value.startswith("json:"):
            try:
                json.loads(value[5:])
            except ValueError:
                raise input_error(path, f"attribute {name} is not valid JSON; rerun the stage that writes it") from None
    stage = _decode_attr(fh.attrs.get(ATTR_STAGE, ""))
    if not isinstance(stage, str) or not stage:
        raise input_error(path, "names no stage that wrote it; not an artefact this mogaf wrote, rerun that stage")
    if stages is not None and stage not in stages:
        raise input_error(path, f"written by stage '{stage}', expected {' or '.join(repr(s) for s in stages)}")
    package = _decode_attr(fh.attrs.get(ATTR_PACKAGE, "?"))
    if not _compatible_package(package):
        raise input_error(path, f"written by mogaf {package}, incompatible with mogaf {__version__}; rerun the stage")
    digest = _decode_attr(fh.attrs.get(ATTR_DIGEST, ""))
    if expected_digest is not None and digest != expected_digest:
        raise input_error(
            path,
            f"config digest {digest} does not match the current configuration ({expected_digest}); rerun the stage",
        )


def _open(path: Path) -> h5py.File:
    if not path.exists():
        raise input_error(path, "missing (run the stage that writes it first)")
    try:
        return h5py.File(path, "r", locking=False)
    except OSError as exc:
        raise input_error(
            path, f"not a readable HDF5 file, truncated or corrupted ({exc.__class__.__name__})"
        ) from None


def _normalise_stages(stage: str | Iterable[str] | None) -> tuple[str, ...] | None:
    if stage is None:
        return None
    if isinstance(stage, str):
        return (stage,)
    return tuple(stage)
