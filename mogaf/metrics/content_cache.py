"""Values computed from images, kept by the images' content.

An evaluation compares every method's render with the same ground-truth
images: what depends on a ground truth alone (its LPIPS features, its SSIM
window statistics) is computed once and found again by content. Least
recently used entries go first once the cache holds more than its bytes.
Threads may share a cache: a value two of them miss at once is computed by
both (the same value) and kept once.
"""

from __future__ import annotations

import hashlib
import threading
from collections.abc import Callable
from typing import Any

import numpy as np


def content_key(*arrays: np.ndarray) -> tuple:
    """Shape, dtype and SHA-1 of each array's bytes (C order)."""
    key: list[Any] = []
    for a in arrays:
        a = np.ascontiguousarray(a)
        key += [a.shape, a.dtype.str, hashlib.sha1(a.tobytes()).hexdigest()]
    return tuple(key)


class ContentCache:
    """key -> value, least recently used first out past `max_bytes`
    (the newest entry stays, whatever its size)."""

    def __init__(self, max_bytes: int = 256 << 20) -> None:
        self.max_bytes = int(max_bytes)
        self.entries: dict[tuple, Any] = {}
        self.sizes: dict[tuple, int] = {}
        self.bytes = 0
        self.lock = threading.Lock()

    def get(self, key: tuple, make: Callable[[], Any], nbytes: Callable[[Any], int]) -> Any:
        with self.lock:
            hit = self.entries.pop(key, None)
            if hit is not None:
                self.entries[key] = hit  # most recently used last
                return hit
        made = make()  # outside the lock: other threads look up and compute meanwhile
        with self.lock:
            hit = self.entries.pop(key, None)
            if hit is None:
                hit = made
                self.sizes[key] = int(nbytes(hit))
                self.bytes += self.sizes[key]
            self.entries[key] = hit
            while self.bytes > self.max_bytes and len(self.entries) > 1:
                old = next(iter(self.entries))
                del self.entries[old]
                self.bytes -= self.sizes.pop(old)
            return hit

    def clear(self) -> None:
        with self.lock:
            self.entries.clear()
            self.sizes.clear()
            self.bytes = 0
