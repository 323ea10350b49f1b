"""How many cores a job's CPU kernels and evaluation use: its own, or more where cores are idle.

A stage asks Snakemake for one core and runs torch on one thread (a fixed
reduction order). The C++ rasterizer gives the same bits for any thread
count (tests/test_render.py), and evaluate's forecasts are measured one by
one with the same results in any order, so both may also use the cores that
no other process is using: the reconstruction when it runs alone, refine and
evaluate, which the demo runs with the second core idle. Where another job
keeps that core busy they stay on one (a second thread there only time-slices).

Idle is measured on Linux from /proc/stat, over this process's CPU set, every
half second: the CPU time all processes spent minus this process's own, and
never more than a cgroup CPU quota allows. MOGAF_CORES=n fixes the count
instead (1: never more than the job's own).
"""

from __future__ import annotations

import contextlib
import math
import os
import threading
import time
from collections.abc import Iterator

ENV = "MOGAF_CORES"
INTERVAL_S = 0.5
FIRST_INTERVAL_S = 0.1  # the first measurement, for a caller that sampled once at its start
# another process's use of a core below this fraction (the workflow's own
# process, the system) still leaves that core to the kernel
SLACK = 0.25


def usable_cores(busy_s: float, own_cpu_s: float, wall_s: float, ncpus: int) -> int:
    """Cores of `ncpus` that other processes left free over an interval of
    `wall_s` seconds in which all processes used `busy_s` CPU seconds on them,
    `own_cpu_s` of it this process's (at least 1)."""
    if wall_s <= 0 or ncpus < 1:
        return 1
    others = max(0.0, busy_s - own_cpu_s) / wall_s
    return max(1, min(ncpus, int(ncpus - others + SLACK)))


def _busy_seconds(cpus: set[int]) -> float | None:
    """CPU seconds spent (not idle, not waiting for I/O) on `cpus` since boot."""
    try:
        with open("/proc/stat", "rb") as f:
            lines = f.read().split(b"\n")
    except OSError:
        return None
    ticks = 0
    seen = 0
    try:
        for line in lines[1:]:
            if not line.startswith(b"cpu"):
                break
            fields = line.split()
            if int(fields[0][3:]) in cpus:
                user, nice, system, idle, iowait, irq, softirq, steal = (int(x) for x in fields[1:9])
                ticks += user + nice + system + irq + softirq + steal
                seen += 1
    except (ValueError, IndexError):  # a layout this reader does not know: no measurement
        return None
    if seen != len(cpus):
        return None
    return ticks / os.sysconf("SC_CLK_TCK")


def quota_cores(
    cpu_max: str | None = None, cfs_quota_us: str | None = None, cfs_period_us: str | None = None
) -> int | None:
    """Whole cores a cgroup CPU quota allows (v2 `cpu.max`, else v1 `cpu.cfs_quota_us`
    and `cpu.cfs_period_us`), rounded up; None without a quota."""
    try:
        if cpu_max is not None:
            quota, _, period = cpu_max.strip().partition(" ")
            if quota == "max":
                return None
            return max(1, math.ceil(int(quota) / int(period or 100000)))
        if cfs_quota_us is not None and cfs_period_us is not None and int(cfs_quota_us) > 0:
            return max(1, math.ceil(int(cfs_quota_us) / int(cfs_period_us)))
    except (ValueError, ZeroDivisionError):
        return None
    return None


def _read(path: str) -> str | None:
    try:
        with open(path) as f:
            return f.read()
    except OSError:
        return None


def _quota_cores() -> int | None:
    """This process's cgroup CPU quota in whole cores (a container's --cpus), if any."""
    v2 = _read("/sys/fs/cgroup/cpu.max")
    if v2 is not None:
        return quota_cores(cpu_max=v2)
    return quota_cores(
        cfs_quota_us=_read("/sys/fs/cgroup/cpu/cpu.cfs_quota_us"),
        cfs_period_us=_read("/sys/fs/cgroup/cpu/cpu.cfs_period_us"),
    )


class _IdleCores:
    """The usable core count, sampled at most every INTERVAL_S seconds."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.cpus = set(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else set()
        # a CPU quota (a container's --cpus) bounds what the CPU set would allow
        self.limit = min(len(self.cpus), _quota_cores() or len(self.cpus))
        self.sample: tuple[float, float, float] | None = None
        self.usable: int | None = None

    def __call__(self) -> int:
        if self.limit < 2:
            return 1
        with self.lock:
            now = time.monotonic()
            if self.sample is not None and now - self.sample[0] < (INTERVAL_S if self.usable else FIRST_INTERVAL_S):
                return self.usable or 1
            busy = _busy_seconds(self.cpus)
            if busy is None:
                self.limit = 1
                return 1
            own = time.process_time()
            if self.sample is not None:
                t0, busy0, own0 = self.sample
                self.usable = min(self.limit, usable_cores(busy - busy0, own - own0, now - t0, len(self.cpus)))
            self.sample = (now, busy, own)
            return self.usable or 1


idle_cores = _IdleCores()
_sharing = {"workers": 1}


def fixed_cores() -> int | None:
    """The core count MOGAF_CORES fixes (None where it is unset or blank);
    a value that is not a whole number >= 1 is an error."""
    fixed = os.environ.get(ENV, "").strip()
    if not fixed:
        return None
    try:
        n = int(fixed)
    except ValueError:
        n = 0
    if n < 1:
        from mogaf.errors import MogafError

        raise MogafError(f"{ENV} must be a whole number >= 1, got {fixed!r}")
    return n


def cores() -> int:
    """Cores this process may use now: MOGAF_CORES, else the idle ones (at least 1)."""
    fixed = fixed_cores()
    return fixed if fixed is not None else idle_cores()


@contextlib.contextmanager
def shared_by(workers: int) -> Iterator[None]:
    """Within the block `workers` threads of this process call the kernels at
    once: each call gets its share of the cores."""
    before = _sharing["workers"]
    _sharing["workers"] = max(1, int(workers))
    try:
        yield
    finally:
        _sharing["workers"] = before


def kernel_threads() -> int:
    """Threads for the next kernel call (at least torch's thread count)."""
    import torch

    return max(1, torch.get_num_threads(), cores() // _sharing["workers"])
