"""glibc's malloc set for the stages' large, short-lived buffers.

An optimisation step allocates and frees buffers of many sizes (images,
per-pixel and per-Gaussian intermediates) every iteration. glibc's own
thresholds, which adapt as the process runs, still hand many of them fresh
pages from the kernel and give freed memory back, so that on larger scenes
(200x200 images, tens of thousands of Gaussians) a step spends much
of its time faulting the same memory in again. Serving blocks up to 32 MiB
from the heap and never trimming it keeps that memory; the process then holds
its peak, which its job reserves anyway. Where the memory comes from changes
no value: results are the same bits.

Only on Linux with glibc, and not where the user set glibc's MALLOC_* tuning
variables (theirs win).
"""

from __future__ import annotations

import ctypes
import os
import platform

M_TRIM_THRESHOLD = -1  # glibc's malloc.h
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 32 * 1024 * 1024  # glibc's largest on 64-bit systems
TRIM_THRESHOLD = 2**31 - 1  # mallopt takes an int: never trim below 2 GiB free
USER_SETTINGS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_TOP_PAD_", "MALLOC_MMAP_MAX_")


def set_thresholds(mmap_threshold: int, trim_threshold: int) -> bool:
    """glibc's mmap and trim thresholds for this process (bytes; fixed from
    here on, no longer adapted); False where glibc is not the C library."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, mmap_threshold)) and bool(mallopt(M_TRIM_THRESHOLD, trim_threshold))


def keep_heap() -> bool:
    """Set the stages' thresholds for this process; False where they are left alone."""
    if any(name in os.environ for name in USER_SETTINGS):
        return False
    return set_thresholds(MMAP_THRESHOLD, TRIM_THRESHOLD)
