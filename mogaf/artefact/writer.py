"""Writing an artefact: nested arrays (finite-checked) plus the standard
attrs and lineage, into an atomic temporary through the guarded sink."""

from __future__ import annotations

import datetime as _dt
import hashlib
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from .. import __version__
from ..errors import input_error
from .atomic import WriteFailed, _GuardedSink, atomic_path
from .header import (
    ATTR_CHECKSUM,
    ATTR_CREATED,
    ATTR_DIGEST,
    ATTR_FORMAT,
    ATTR_PACKAGE,
    ATTR_STAGE,
    FORMAT_VERSION,
    RESERVED_ATTRS,
    _attr_value,
    dataset_checksum,
)
from .lineage import _lineage_attrs


def _check_finite(name: str, arr: np.ndarray, path: Path) -> None:
    if arr.dtype.kind in "fc" and not np.all(np.isfinite(arr)):
        bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
        raise input_error(path, f"refusing to write non-finite values in '{name}' ({bad} of {arr.size})")


def _write_tree(group: h5py.Group, data: Mapping[str, Any], path: Path, prefix: str = "", content: Any = None) -> None:
    """Write `data` under `group`; `content` (a hashlib object), if given,
    takes in every entry's name, type, shape and values in key order."""
    for key, value in sorted(data.items()):
        if "/" in key:
            raise ValueError(f"artefact key {key!r} may not contain '/': use nested mappings")
        name = f"{prefix}{key}"
        if value is None:
            continue
        if isinstance(value, Mapping):
            _write_tree(group.create_group(key), value, path, prefix=f"{name}/", content=content)
            continue
        if isinstance(value, (list, tuple)) and value and all(isinstance(v, str) for v in value):
            value = np.array(value)
        arr = np.asarray(value)
        if arr.dtype == object:
            raise TypeError(f"artefact entry {name!r} has object dtype")
        if content is not None:
            content.update(f"{name}\0{arr.dtype.str}\0{arr.shape}\0".encode())
            content.update(np.ascontiguousarray(arr))  # the buffer itself: no copy of a big array
        if arr.dtype.kind == "U":
            ds = group.create_dataset(key, data=arr.astype(h5py.string_dtype()))
            ds.attrs[ATTR_CHECKSUM] = dataset_checksum(arr)
            continue
        _check_finite(name, arr, path)
        if arr.ndim == 0 or arr.size == 0:  # HDF5 filters need chunks, which these cannot have
            ds = group.create_dataset(key, data=arr)
            ds.attrs[ATTR_CHECKSUM] = dataset_checksum(arr)
            continue
        # Fletcher-32 per chunk: HDF5 checks it on every read, partial reads included.
        # gzip level 1 for large arrays keeps images small and fast.
        kwargs: dict[str, Any] = {"fletcher32": True}
        if arr.size >= 1 << 16:
            kwargs.update(compression="gzip", compression_opts=1, shuffle=True)
        group.create_dataset(key, data=arr, **kwargs)


def write_artefact(
    path: str | os.PathLike,
    stage: str,
    data: Mapping[str, Any],
    *,
    config_digest: str,
    attrs: Mapping[str, Any] | None = None,
) -> Path:
    """Write `data` (nested mapping of arrays) atomically with standard attrs.

    Scalars and small metadata go in `attrs` (mappings and lists are stored
    as JSON text). Floating-point arrays must be finite.
    """
    final = Path(path)
    attrs = dict(attrs or {})
    for key in attrs:
        if key in RESERVED_ATTRS:
            raise ValueError(f"attribute {key!r} is reserved")
    with atomic_path(final) as tmp:
        sink = _GuardedSink(tmp)
        try:
            with h5py.File(sink, "w", locking=False) as fh:
                fh.attrs[ATTR_FORMAT] = FORMAT_VERSION
                fh.attrs[ATTR_STAGE] = stage
                fh.attrs[ATTR_DIGEST] = config_digest
                fh.attrs[ATTR_PACKAGE] = __version__
                fh.attrs[ATTR_CREATED] = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
                for key, value in attrs.items():
                    if value is not None:
                        fh.attrs[key] = _attr_value(value)
                content = hashlib.blake2b(digest_size=16)
                _write_tree(fh, data, final, content=content)
                for key, value in _lineage_attrs(stage, config_digest, content.hexdigest()).items():
                    fh.attrs[key] = value
        finally:
            sink.close()
        if sink.error is not None:
            raise WriteFailed(sink.error)
    return final
