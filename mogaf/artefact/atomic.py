"""Atomic writes: a hidden temporary renamed into place only when complete,
removed on any failure; a full disk (or quota) is one line naming the output;
the guarded sink that keeps HDF5 from seeing a failed write; JSON files."""

from __future__ import annotations

import contextlib
import errno
import glob
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from ..errors import MogafError, input_error

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
        full = no_space_error(exc)
        if full is not None:
            raise write_error(final, full) from None
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


def no_space_error(exc: BaseException) -> OSError | None:
    """`exc` as the full-disk OSError it stands for, or None. Libraries that
    write through their own code report a full disk in their own words (an
    encoder subprocess's text, say); those words are recognised here."""
    if isinstance(exc, OSError) and exc.errno in NO_SPACE_ERRNOS:
        return exc
    if "No space left on device" in str(exc) or "Disk quota exceeded" in str(exc):
        return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    return None


def write_bytes(path: str | os.PathLike, data: bytes | bytearray | memoryview) -> Path:
    """Atomically write `data` (encoded in memory first, e.g. a checkpoint or
    an image), so a full disk is one line naming `path` and leaves nothing."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(data)
    return Path(path)


@contextlib.contextmanager
def atomic_folder(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a hidden temporary folder beside `path`; it replaces `path` (a
    folder, replaced whole) only if the block succeeds, and is removed on any
    failure. A full disk met inside becomes one line naming `path`."""
    import shutil

    final = Path(path)
    tmp = _temp_name(final)
    if final.exists() and not final.is_dir():
        raise input_error(final, "is an existing file; the output must be a folder")
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        for stale in glob.glob(str(final.with_name(f".{final.name}.tmp-*"))):
            shutil.rmtree(stale, ignore_errors=True)
        _check_room(final)
        tmp.mkdir()
    except OSError as exc:
        raise write_error(final, exc) from None
    try:
        yield tmp
        if final.exists():
            old = final.with_name(f"{tmp.name}-old")
            os.replace(final, old)
            os.replace(tmp, final)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, final)
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        full = no_space_error(exc)
        if full is not None:  # reported once the temporary is gone, so the room said to be left is right
            raise write_error(final, full) from None
        raise


def write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Atomically write JSON (sorted keys, finite numbers only)."""
    with atomic_path(path) as tmp:
        with open(tmp, "w") as fh:
            json.dump(obj, fh, indent=2, sort_keys=True, allow_nan=False)
            fh.write("\n")
    return Path(path)
