"""Loading DyCheck/Shape-of-Motion per-frame files: .npy depth and disparity
(header-checked before reading), 2D tracks, background points, binary PNG
masks, and the thread pool the frames are loaded with."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from ...errors import input_error
from ..images import read_image

# np.load parses .npy headers with ast.literal_eval, which CPython 3.11 does not
# allow from several threads at once (spurious "AST constructor recursion depth
# mismatch" SystemError): headers are parsed one at a time, data is read lazily.
_NPY_LOCK = threading.Lock()


def _open_npy(path: Path):
    with _NPY_LOCK:
        return np.load(path, mmap_mode="r", allow_pickle=False)


def _load_npy(path: Path, shape2d: tuple[int, int], what: str) -> np.ndarray:
    """A float (H, W) or (H, W, 1) array, header-checked before reading."""
    try:
        arr = _open_npy(path)
    except FileNotFoundError:
        raise input_error(path, f"missing {what}") from None
    except (ValueError, OSError, EOFError, TypeError) as exc:
        raise input_error(
            path,
            f"unreadable or corrupt .npy {what} ({str(exc).splitlines()[0] if str(exc) else exc.__class__.__name__})",
        ) from None
    if not isinstance(arr, np.ndarray):
        raise input_error(path, f"{what} is not a plain array")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.shape != shape2d:
        raise input_error(path, f"{what} has shape {arr.shape}, expected {shape2d} (the rgb image size)")
    if arr.dtype.kind not in "fiu":
        raise input_error(path, f"{what} has dtype {arr.dtype}, expected numbers")
    try:
        out = np.array(arr, dtype=np.float32)
    except (ValueError, OSError) as exc:
        raise input_error(path, f"unreadable or truncated .npy {what} ({exc.__class__.__name__})") from None
    if not np.all(np.isfinite(out)):
        raise input_error(path, f"{what} has NaN or infinite values")
    return out


def _load_tracks(path: Path) -> np.ndarray:
    try:
        arr = _open_npy(path)
    except FileNotFoundError:
        raise input_error(path, "missing 2D-track file (every train frame pair must have one)") from None
    except (ValueError, OSError, EOFError, TypeError) as exc:
        raise input_error(path, f"unreadable or corrupt .npy tracks ({exc.__class__.__name__})") from None
    if not isinstance(arr, np.ndarray) or arr.ndim != 2 or arr.shape[1] != 4 or arr.dtype.kind not in "fiu":
        raise input_error(path, f"2D tracks must be a (P, 4) numeric array, got {getattr(arr, 'shape', '?')}")
    return arr


def _binary_mask(path: Path, size: tuple[int, int], what: str) -> np.ndarray:
    img = read_image(path, expect_size=size, what=what)
    if img.ndim == 3:
        img = img[..., :3].max(axis=2) if img.shape[2] >= 3 else img.max(axis=2)
    thr = 1 if int(img.max(initial=0)) <= 1 else 128
    return (img >= thr).astype(np.uint8)


def _run(fn, n: int, workers: int) -> None:
    if workers <= 1 or n <= 1:
        for i in range(n):
            fn(i)
        return
    with ThreadPoolExecutor(max_workers=workers) as pool:
        list(pool.map(fn, range(n)))


def _points(path: Path) -> np.ndarray:
    try:
        arr = _open_npy(path)
    except (ValueError, OSError, EOFError, TypeError) as exc:
        raise input_error(path, f"unreadable or corrupt .npy points ({exc.__class__.__name__})") from None
    if not isinstance(arr, np.ndarray) or arr.ndim != 2 or arr.shape[1] not in (3, 6) or arr.dtype.kind not in "fiu":
        raise input_error(path, f"points must be an (N, 3) or (N, 6) array, got {getattr(arr, 'shape', '?')}")
    pts = np.array(arr, dtype=np.float64)
    if not np.all(np.isfinite(pts)):
        raise input_error(path, "points have non-finite values")
    if pts.shape[1] == 3:
        pts = np.concatenate([pts, np.full_like(pts, 0.5)], axis=1)
    return pts.astype(np.float32)


def _tracks(tdir: Path, names, splits, time_index, q_stride: int, max_points: int, workers: int) -> dict:
    train = [f for f in range(len(names)) if splits[f] == "train"]
    queries = train[::q_stride]
    M = len(train)
    per_query: list[np.ndarray | None] = [None] * len(queries)

    def load_query(qi: int) -> None:
        q = queries[qi]
        first = _load_tracks(tdir / f"{names[q]}_{names[q]}.npy")
        P = first.shape[0]
        keep = (
            np.arange(P)
            if not max_points or max_points >= P
            else np.unique(np.linspace(0, P - 1, max_points).round().astype(np.int64))
        )
        block = np.empty((keep.size, M, 4), np.float32)
        for j, t in enumerate(train):
            path = tdir / f"{names[q]}_{names[t]}.npy"
            arr = first if t == q else _load_tracks(path)
            if arr.shape[0] != P:
                raise input_error(path, f"has {arr.shape[0]} tracks, but query frame {names[q]} has {P}")
            try:
                vals = np.asarray(arr[keep], dtype=np.float32)
            except (ValueError, OSError) as exc:
                raise input_error(path, f"unreadable or truncated .npy tracks ({exc.__class__.__name__})") from None
            if not np.all(np.isfinite(vals)):
                raise input_error(path, "2D tracks have NaN or infinite values")
            block[:, j] = vals
        block[..., :2] += 0.5  # TAPIR/SoM pixel centres are integers; mogaf's are at +0.5
        per_query[qi] = block

    _run(load_query, len(queries), workers)
    counts = [b.shape[0] for b in per_query]
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    values = np.concatenate(per_query, axis=0) if per_query else np.zeros((0, M, 4), np.float32)
    return {
        "query_frame": np.array(queries, np.int64),
        "query_time_index": np.asarray(time_index)[queries],
        "target_frame": np.array(train, np.int64),
        "target_time_index": np.asarray(time_index)[train],
        "offsets": offsets,
        "values": values,
    }
