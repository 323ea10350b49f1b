"""HDF5 artefacts: the files every stage writes and the next one reads.

Guarantees:
- a write goes to a hidden temporary name in the same folder and is renamed
  into place only when complete, so a killed stage leaves no partial artefact;
  a write that fails (a full disk, a quota, an I/O error) removes it and is
  one line naming the output;
- every artefact carries attrs: format version, stage, config digest,
  package version, UTC creation time;
- non-finite floating-point arrays are refused on write and on read;
- inputs are opened read-only with HDF5 file locking off (clusters with NFS);
- a reader checks the attrs and fails with one line naming the file;
- lineage: an artefact written inside `stage_inputs` records the lineage
  digests of the artefacts it was made from, and its own (a digest of its
  config digest, those, and its arrays' contents); inputs read together must
  agree (`check_lineage`). A deterministic rerun with the same settings keeps
  its digest; a rerun that writes other values (another machine, a GPU) gets
  a new one, so files made from the old one are refused until rerun.
"""

from __future__ import annotations

import contextlib
import contextvars
import datetime as _dt
import errno
import glob
import hashlib
import json
import os
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from . import __version__
from .errors import MogafError, input_error

FORMAT_VERSION = 1

ATTR_FORMAT = "mogaf_format_version"
ATTR_STAGE = "mogaf_stage"
ATTR_DIGEST = "mogaf_config_digest"
ATTR_PACKAGE = "mogaf_package_version"
ATTR_CREATED = "mogaf_created_utc"
# Lineage: a digest of the artefact's config digest and its inputs' lineage
# digests, and those inputs' lineage digests by stage (see `stage_inputs`).
ATTR_LINEAGE = "mogaf_lineage_digest"
ATTR_INPUTS = "mogaf_input_digests"
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


# ---------------------------------------------------------------- atomic files
# errno values that mean "the file system has no room for this file".
NO_SPACE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG})


def _temp_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.tmp-{os.getpid()}")


def remove_stale_temps(path: str | os.PathLike) -> None:
    """Delete temporaries left by a killed writer of `path`."""
    p = Path(path)
    for stale in glob.glob(str(p.with_name(f".{p.name}.tmp-*"))):
        with contextlib.suppress(OSError):
            os.remove(stale)


def free_bytes(folder: str | os.PathLike) -> int | None:
    """Bytes an unprivileged writer may still use in `folder`'s file system
    (None where the file system does not say, e.g. some network mounts)."""
    try:
        st = os.statvfs(folder)
    except OSError:
        return None
    if st.f_blocks == 0:  # a file system that reports no size reports no free space either
        return None
    return int(st.f_bavail) * int(st.f_frsize)


def _size_text(nbytes: int) -> str:
    if nbytes < 1024:
        return f"{nbytes} bytes"
    size = float(nbytes)
    for unit in ("KiB", "MiB", "GiB"):  # noqa: B007 (the last unit is the one printed)
        size /= 1024
        if size < 1024:
            break
    return f"{size:.1f} {unit}"


def write_error(path: str | os.PathLike, exc: OSError) -> MogafError:
    """One line for a failed write of `path`: a full disk says so, with the
    room left there; any other error gives the system's reason."""
    final = Path(path)
    if exc.errno in NO_SPACE_ERRNOS:
        free = free_bytes(final.parent)
        room = "" if free is None else f" ({_size_text(free)} free there)"
        return input_error(final, f"cannot be written: no space left on device{room}; free some space and rerun")
    return input_error(final, f"cannot be written ({exc.strerror or exc.__class__.__name__})")


def _check_room(final: Path) -> None:
    """Refuse a write into a file system with no room left before anything is opened."""
    if free_bytes(final.parent) == 0:
        raise write_error(final, OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)))


def _check_not_directory(final: Path) -> None:
    if final.is_dir():
        raise input_error(final, "is an existing directory; the output must be a file path")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path; rename it to `path` only if the block succeeds.

    The temporary is removed on every failure; a full disk met inside the
    block becomes one line naming `path`."""
    final = Path(path)
    tmp = _temp_name(final)
    _check_not_directory(final)
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        _check_room(final)
        remove_stale_temps(final)
        open(tmp, "wb").close()  # fail here, with the output's name, where it cannot be written
    except OSError as exc:
        raise write_error(final, exc) from None
    try:
        yield tmp
        os.replace(tmp, final)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        # reported once the temporary is gone, so the room said to be left is right
        if isinstance(exc, WriteFailed):
            raise write_error(final, exc.error) from None
        if isinstance(exc, OSError) and exc.errno in NO_SPACE_ERRNOS:
            raise write_error(final, exc) from None
        raise


class WriteFailed(Exception):
    """Raised inside an `atomic_path` block for a write that failed out of
    Python's sight (see `_GuardedSink`); `atomic_path` reports it."""

    def __init__(self, error: OSError) -> None:
        super().__init__(str(error))
        self.error = error


class _GuardedSink:
    """The temporary file of an HDF5 write, handed to h5py as a file object.

    HDF5 does not survive its own writes failing: on a full disk h5py prints
    dozens of tracebacks while closing and then segfaults, leaving the
    temporary behind. So HDF5 never sees a failure here: the first failed
    write is kept in `error`, every later write is dropped (reading dropped
    bytes gives zeros), HDF5 closes normally, and the caller reports `error`.
    """

    def __init__(self, path: Path) -> None:
        self._fh = open(path, "r+b", buffering=0)  # noqa: SIM115 (closed by close()); unbuffered: a failure surfaces at its write
        self.error: OSError | None = None
        self._pos = 0
        self._end = 0

    def _fail(self, exc: OSError) -> None:
        if self.error is None:
            self.error = exc

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        base = {os.SEEK_SET: 0, os.SEEK_CUR: self._pos, os.SEEK_END: self._end}[whence]
        self._pos = base + offset
        return self._pos

    def tell(self) -> int:
        return self._pos

    def write(self, data) -> int:
        view = memoryview(data).cast("B")
        if self.error is None:
            try:
                done = 0
                while done < len(view):  # an unbuffered write may take only part of it
                    done += os.pwrite(self._fh.fileno(), view[done:], self._pos + done)
            except OSError as exc:
                self._fail(exc)
        self._pos += len(view)
        self._end = max(self._end, self._pos)
        return len(view)

    def readinto(self, buffer) -> int:
        view = memoryview(buffer).cast("B")
        got = 0
        try:  # what was written before a failure is still there to read
            got = os.preadv(self._fh.fileno(), [view], self._pos)
        except OSError as exc:
            self._fail(exc)
        view[got:] = b"\0" * (len(view) - got)
        self._pos += len(view)
        return len(view)

    def read(self, size: int = -1) -> bytes:
        size = max(self._end - self._pos, 0) if size is None or size < 0 else size
        buffer = bytearray(size)
        self.readinto(buffer)
        return bytes(buffer)

    def truncate(self, size: int | None = None) -> int:
        size = self._pos if size is None else int(size)
        if self.error is None:
            try:
                os.ftruncate(self._fh.fileno(), size)
            except OSError as exc:
                self._fail(exc)
        self._end = size
        return size

    def flush(self) -> None:
        pass  # unbuffered: nothing is held here

    def close(self) -> None:
        try:
            self._fh.close()  # network file systems may report a failed write only here
        except OSError as exc:
            self._fail(exc)


def write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Atomically write JSON (sorted keys, finite numbers only)."""
    with atomic_path(path) as tmp:
        with open(tmp, "w") as fh:
            json.dump(obj, fh, indent=2, sort_keys=True, allow_nan=False)
            fh.write("\n")
    return Path(path)


# ---------------------------------------------------------------- writing
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
            group.create_dataset(key, data=arr.astype(h5py.string_dtype()))
            continue
        _check_finite(name, arr, path)
        # Chunked + gzip level 1 for large arrays keeps images small and fast.
        kwargs: dict[str, Any] = {}
        if arr.size >= 1 << 16:
            kwargs = {"compression": "gzip", "compression_opts": 1, "shuffle": True}
        group.create_dataset(key, data=arr, **kwargs)


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


# ---------------------------------------------------------------- lineage
@dataclass(frozen=True)
class Lineage:
    path: Path
    stage: str
    digest: str  # "" when the file predates lineage records
    inputs: Mapping[str, tuple[str, ...]]  # input stage -> lineage digests of the inputs it was made from


_STAGE_INPUTS: contextvars.ContextVar[tuple[Lineage, ...]] = contextvars.ContextVar("mogaf_stage_inputs", default=())


def read_lineage(path: str | os.PathLike) -> Lineage:
    p = Path(path)
    with _open(p) as fh:
        _check_header(fh, p, None, None)
        inputs = _decode_attr(fh.attrs.get(ATTR_INPUTS, "json:{}"))
        return Lineage(
            p,
            _decode_attr(fh.attrs[ATTR_STAGE]),
            _decode_attr(fh.attrs.get(ATTR_LINEAGE, "")),
            {str(k): tuple(v) for k, v in dict(inputs).items()},
        )


def check_lineage(artefacts: Iterable[Lineage]) -> None:
    """Inputs read together must come from one lineage of settings: an
    artefact made from another upstream artefact than the one given (other
    settings, a split of another scene, groups of another reconstruction) is
    refused with one line naming both files. Files that record no lineage
    (written outside a stage, or before lineage existed) are not checked."""
    given = list(artefacts)
    for a in given:
        for b in given:
            made_from = a.inputs.get(b.stage)
            if b is a or made_from is None or not b.digest:
                continue
            if b.digest not in made_from:
                raise input_error(
                    a.path,
                    f"was made from another '{b.stage}' artefact than {b.path} "
                    "(other settings or inputs); rerun the stages after it",
                )


def check_made_from(derived: str | os.PathLike, source: str | os.PathLike) -> None:
    """`derived` must have been made from `source` itself, not merely from
    something of one lineage with it (e.g. a measurement of recon.h5 where
    refined.h5 is meant). Files that record no lineage are not checked."""
    made, src = read_lineage(derived), read_lineage(source)
    if not made.digest or not src.digest:
        return
    if src.digest not in made.inputs.get(src.stage, ()):
        made_of = ", ".join(f"'{stage}'" for stage in sorted(made.inputs)) or "nothing recorded"
        raise input_error(
            made.path,
            f"was not made from {src.path} (a '{src.stage}' artefact; it was made from "
            f"{made_of}); rerun the stage that writes it",
        )


@contextlib.contextmanager
def stage_inputs(*paths: str | os.PathLike | None) -> Iterator[tuple[Lineage, ...]]:
    """Declare the artefacts a stage reads. They are checked to share one
    lineage, and every artefact written inside the block records them."""
    found = tuple(read_lineage(p) for p in paths if p is not None and Path(p).is_file())
    check_lineage(found)
    token = _STAGE_INPUTS.set(found)
    try:
        yield found
    finally:
        _STAGE_INPUTS.reset(token)


def _lineage_attrs(stage: str, digest: str, content: str) -> dict[str, str]:
    inputs: dict[str, list[str]] = {}
    for item in _STAGE_INPUTS.get():
        inputs.setdefault(item.stage, []).append(item.digest)
    inputs = {k: sorted(v) for k, v in sorted(inputs.items())}
    lineage = config_digest({"stage": stage, "config": digest, "inputs": inputs, "content": content})
    return {ATTR_LINEAGE: lineage, ATTR_INPUTS: _attr_value(inputs)}


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


# ---------------------------------------------------------------- reading
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
    stage = _decode_attr(fh.attrs.get(ATTR_STAGE, ""))
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


class ArtefactAttrs(dict):
    """An artefact's attrs; a missing one is an input error naming the file."""

    def __init__(self, path: Path, stage: str, items: Mapping[str, Any]) -> None:
        super().__init__(items)
        self._where = (path, stage)

    def __missing__(self, key: str) -> Any:
        path, stage = self._where
        raise input_error(path, f"has no attribute '{key}' (stage {stage})")


@dataclass
class Artefact:
    """An artefact read into memory: nested dict of arrays plus attrs."""

    path: Path
    stage: str
    config_digest: str
    package_version: str
    created_utc: str
    attrs: dict[str, Any]
    data: dict[str, Any] = field(repr=False)

    def _lookup(self, key: str) -> Any:
        node: Any = self.data
        for part in key.split("/"):
            node = node[part]
        return node

    def __getitem__(self, key: str) -> Any:
        try:
            return self._lookup(key)
        except KeyError:
            raise input_error(self.path, f"has no entry '{key}' (stage {self.stage})") from None

    def __contains__(self, key: str) -> bool:
        try:
            self._lookup(key)
        except KeyError:
            return False
        return True

    def get(self, key: str, default: Any = None) -> Any:
        try:
            return self._lookup(key)
        except KeyError:
            return default


def read_dataset(ds: h5py.Dataset, path: Path, name: str | None = None, sel: Any = None) -> Any:
    """One dataset (or the part `sel` indexes), finite-checked; strings decoded."""
    name = name or ds.name.lstrip("/")
    try:
        if h5py.check_string_dtype(ds.dtype) is not None:
            arr = ds.asstr()[()] if sel is None else ds.asstr()[sel]
            return arr.tolist() if isinstance(arr, np.ndarray) else arr
        arr = ds[()] if sel is None else ds[sel]
    except (OSError, RuntimeError) as exc:
        raise input_error(
            path, f"entry '{name}' cannot be read, file truncated or corrupted ({exc.__class__.__name__})"
        ) from None
    if isinstance(arr, np.ndarray) and arr.dtype.kind in "fc" and not np.all(np.isfinite(arr)):
        raise input_error(path, f"entry '{name}' contains non-finite values (corrupted artefact); rerun the stage")
    return arr


def read_tree(
    group: h5py.Group, path: Path, prefix: str = "", selection: Callable[[str, h5py.Dataset], Any] | None = None
) -> dict[str, Any]:
    """Every dataset under `group`, finite-checked. `selection(key, dataset)`
    may return an index to read only part of a dataset (None: all of it)."""
    out: dict[str, Any] = {}
    for key, item in group.items():
        name = f"{prefix}{key}"
        if isinstance(item, h5py.Group):
            out[key] = read_tree(item, path, prefix=f"{name}/", selection=selection)
            continue
        out[key] = read_dataset(item, path, name, None if selection is None else selection(key, item))
    return out


def time_steps_index(steps: np.ndarray, num_steps: int | None = None) -> slice | np.ndarray:
    """Index for a time axis (of `num_steps` steps, if given) that reads only
    `steps` off disk: a contiguous range is one slice (fast in HDF5), any
    other set an increasing index."""
    steps = np.asarray(steps, np.int64)
    if not steps.size:
        return slice(0, 0)
    if steps.min() < 0 or (num_steps is not None and steps.max() >= num_steps):
        upper = "" if num_steps is None else f" of {num_steps}"
        raise MogafError(f"time steps {int(steps.min())}..{int(steps.max())} lie outside the time axis{upper}")
    if np.array_equal(steps, np.arange(steps[0], steps[-1] + 1)):
        return slice(int(steps[0]), int(steps[-1]) + 1)
    if steps.size > 1 and np.any(np.diff(steps) <= 0):
        raise MogafError("time steps to read are not increasing")
    return steps


def read_artefact(
    path: str | os.PathLike,
    stage: str | Iterable[str] | None = None,
    *,
    expected_config_digest: str | None = None,
    required: Iterable[str] = (),
) -> Artefact:
    """Read a whole artefact, checking attrs, required entries and finiteness."""
    p = Path(path)
    with _open(p) as fh:
        _check_header(fh, p, _normalise_stages(stage), expected_config_digest)
        stage_name = _decode_attr(fh.attrs[ATTR_STAGE])
        attrs = ArtefactAttrs(
            p, stage_name, {k: _decode_attr(v) for k, v in fh.attrs.items() if k not in RESERVED_ATTRS}
        )
        data = read_tree(fh, p)
        art = Artefact(
            path=p,
            stage=stage_name,
            config_digest=_decode_attr(fh.attrs.get(ATTR_DIGEST, "")),
            package_version=_decode_attr(fh.attrs.get(ATTR_PACKAGE, "")),
            created_utc=_decode_attr(fh.attrs.get(ATTR_CREATED, "")),
            attrs=attrs,
            data=data,
        )
    for key in required:
        if key not in art:
            raise input_error(p, f"has no entry '{key}' (stage {art.stage})")
    return art


@contextlib.contextmanager
def open_artefact(
    path: str | os.PathLike,
    stage: str | Iterable[str] | None = None,
    *,
    expected_config_digest: str | None = None,
) -> Iterator[h5py.File]:
    """Open an artefact read-only for partial reads (e.g. selected frames).

    The header is checked; finiteness is the caller's job (see `read_rows`).
    """
    p = Path(path)
    fh = _open(p)
    try:
        _check_header(fh, p, _normalise_stages(stage), expected_config_digest)
        yield fh
    except KeyError as exc:
        # h5py's KeyError for an absent entry or attribute: one line naming the file
        # (a KeyError of the caller's own code is left alone: it is not the file's fault)
        tb = exc.__traceback__
        while tb is not None and tb.tb_next is not None:
            tb = tb.tb_next
        if tb is None or "h5py" not in tb.tb_frame.f_code.co_filename:
            raise
        detail = exc.args[0] if exc.args else exc
        raise input_error(p, f"lacks an entry or attribute its reader needs ({detail})") from None
    finally:
        fh.close()


def read_rows(fh: h5py.File, key: str, rows: np.ndarray) -> np.ndarray:
    """Read only `rows` (first axis) of dataset `key`, checking finiteness."""
    path = Path(fh.filename)
    if key not in fh:
        raise input_error(path, f"has no entry '{key}'")
    rows = np.asarray(rows, dtype=np.int64)
    ds = fh[key]
    if rows.size and (rows.min() < 0 or rows.max() >= ds.shape[0]):
        raise input_error(path, f"entry '{key}' has {ds.shape[0]} rows, asked for row {int(rows.max())}")
    try:
        order = np.argsort(rows, kind="stable")
        sorted_rows = rows[order]
        unique_rows, inverse = np.unique(sorted_rows, return_inverse=True)
        block = ds[unique_rows] if unique_rows.size else np.empty((0,) + ds.shape[1:], ds.dtype)
    except (OSError, RuntimeError) as exc:
        raise input_error(
            path, f"entry '{key}' cannot be read, file truncated or corrupted ({exc.__class__.__name__})"
        ) from None
    out = np.empty((rows.size,) + ds.shape[1:], dtype=ds.dtype)
    out[order] = block[inverse]
    if out.dtype.kind in "fc" and not np.all(np.isfinite(out)):
        raise input_error(path, f"entry '{key}' contains non-finite values in the requested rows (corrupted artefact)")
    return out


def read_attrs(path: str | os.PathLike, stage: str | Iterable[str] | None = None) -> dict[str, Any]:
    """Read only the attrs (header checked)."""
    with open_artefact(path, stage) as fh:
        return {k: _decode_attr(v) for k, v in fh.attrs.items()}
