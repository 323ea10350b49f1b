"""glibc's malloc thresholds for the stages (mogaf.allocator)."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

from mogaf import stages
from mogaf.allocator import USER_SETTINGS

glibc = pytest.mark.skipif(
    platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="the thresholds are glibc's"
)

# Buffers of 1-24 MiB, five alive at a time, as a training step's
# intermediates come and go; prints keep_heap's answer and the minor page
# faults (memory handed in fresh by the kernel) the loop caused.
CHURN = """
import ctypes, resource, sys
import numpy as np
ctypes.CDLL(None).prctl(41, 1, 0, 0, 0)  # PR_SET_THP_DISABLE: 4 KiB pages, so faults count the same memory anywhere
from mogaf.allocator import keep_heap
kept = keep_heap() if sys.argv[1] == "kept" else None
sizes = np.random.default_rng(0).integers(1, 25, size=300) << 20
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
live = []
for size in sizes:
    block = np.empty(int(size), np.uint8)
    block[::4096] = 1
    live = live[-4:] + [block]
print(kept, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _churn(how: str, env: dict[str, str] | None = None) -> tuple[str, int]:
    clean = {k: v for k, v in os.environ.items() if k not in USER_SETTINGS}
    res = subprocess.run(
        [sys.executable, "-c", CHURN, how], capture_output=True, text=True, timeout=120, env={**clean, **(env or {})}
    )
    assert res.returncode == 0, res.stderr[-2000:]
    kept, faults = res.stdout.split()
    return kept, int(faults)


@glibc
def test_kept_heap_reuses_memory_instead_of_faulting_it_in_again():
    kept, faults_kept = _churn("kept")
    _, faults_default = _churn("default")
    assert kept == "True"
    # ~300 blocks of 12 MiB on average: glibc's own thresholds fault in most of them afresh
    assert faults_kept * 3 < faults_default, (faults_kept, faults_default)


@glibc
def test_the_users_malloc_settings_win():
    kept, _ = _churn("kept", {"MALLOC_TRIM_THRESHOLD_": "131072"})
    assert kept == "False"


def test_every_stage_sets_the_thresholds(monkeypatch):
    calls = []
    monkeypatch.setattr(stages, "keep_heap", lambda: calls.append(True))
    assert stages.run_stage(lambda: 7) == 7
    assert calls == [True]
