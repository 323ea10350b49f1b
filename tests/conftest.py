"""Shared fixtures and the suite's defaults. Tests never need ../shared/data; those that use it skip.

The helpers behind the fixtures live in tests/support/ (plain modules, not
test modules): pytest imports this file in its default "prepend" import
mode, which puts tests/ first on sys.path, in the main process and in every
xdist worker, so test modules import them as `from support.<module> import ...`.

Tests marked `slow` are deselected unless selected: `-m slow` (or any -m
expression naming `slow`) or `--run-slow` runs them.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from support.paths import REPO

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


# ------------------------------------------------------------------ slow tests
def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--run-slow",
        action="store_true",
        default=False,
        help="also run the tests marked slow (deselected by default; -m slow selects them too)",
    )


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Put the `long` modules first, longest first, then deselect `slow` tests
    unless the user asked for them (--run-slow, or a -m expression naming slow).

    xdist (--dist loadfile) hands out test files in collection order: a
    long module collected late keeps one worker busy after the other has run
    out of files, so the long ones start first, in the order of the seconds
    their marker gives (`pytest.mark.long(seconds=...)`, measured with two
    workers): longest first balances the workers."""

    def seconds(item: pytest.Item) -> float:
        marker = item.get_closest_marker("long")
        return float(marker.kwargs.get("seconds", 60.0)) if marker is not None else 0.0

    items.sort(key=lambda item: -seconds(item))  # stable: the order within stays
    if config.getoption("--run-slow") or "slow" in (config.getoption("markexpr") or ""):
        return
    slow = [item for item in items if item.get_closest_marker("slow") is not None]
    if slow:
        config.hook.pytest_deselected(items=slow)
        items[:] = [item for item in items if item.get_closest_marker("slow") is None]
    if hasattr(config, "workeroutput"):  # an xdist worker: tell the controller, which shows no deselections
        config.workeroutput["slow_deselected"] = len(slow)


_SLOW_ON_WORKERS: list[int] = []


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error) -> None:
    """xdist controller: note how many slow tests a worker deselected (each worker collects the whole run)."""
    _SLOW_ON_WORKERS.append(getattr(node, "workeroutput", {}).get("slow_deselected", 0))


def pytest_terminal_summary(terminalreporter, exitstatus: int, config: pytest.Config) -> None:
    if _SLOW_ON_WORKERS and max(_SLOW_ON_WORKERS):
        terminalreporter.write_line(
            f"{max(_SLOW_ON_WORKERS)} slow tests deselected (run them with -m slow or --run-slow)"
        )


# ------------------------------------------------------------------ fixtures
@pytest.fixture
def restore_root_logging():
    """mogaf.stages.run_stage (the CLI's) replaces the root logger's handlers: put pytest's back after the test."""
    import logging

    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    for handler in list(root.handlers):
        root.removeHandler(handler)
        if handler not in handlers:
            handler.close()
    for handler in handlers:
        root.addHandler(handler)
    root.setLevel(level)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(0)


@pytest.fixture
def fake_dnerf_scene(tmp_path: Path) -> Path:
    """A tiny D-NeRF scene at the fake's defaults (support.fake_datasets), in tmp_path/s."""
    from support.fake_datasets import fake_dnerf

    return fake_dnerf(tmp_path / "s")


@pytest.fixture
def fake_iphone_scene(tmp_path: Path) -> Path:
    """A tiny DyCheck iPhone (+ Shape-of-Motion) scene at the fake's defaults, in tmp_path/s."""
    from support.fake_datasets import fake_iphone

    return fake_iphone(tmp_path / "s")


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """scene.h5, split.h5 and priors.h5 of the tiny rendered scene (support.tiny_scene), once per module."""
    from support.tiny_scene import make_tiny_scene

    return make_tiny_scene(tmp_path_factory.mktemp("tiny"))
