"""Shared fixtures. Tests never need ../shared/data; those that use it skip."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = (REPO.parent / "shared" / "data").resolve()

# Tests share the repository's cache (compiled kernels, LPIPS weights), and
# matplotlib's too, whichever test file a pytest worker runs first.
os.environ.setdefault("MOGAF_CACHE_DIR", str(REPO / ".cache" / "mogaf"))
os.environ.setdefault("MPLCONFIGDIR", str(Path(os.environ["MOGAF_CACHE_DIR"]) / "matplotlib"))

if os.environ.get("PYTEST_XDIST_WORKER"):
    # One pytest worker per core (make test): one torch thread each, in the
    # worker and in the Python processes it starts, so the workers do not
    # oversubscribe the cores and a test's child computes as its parent does
    # (pipeline stages set their own thread count).
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)


def shared_path(*parts: str) -> Path:
    """A path under ../shared/data, or skip the test with a clear reason."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"needs {path} (the read-only shared data folder beside the clone); absent here")
    return path


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)
