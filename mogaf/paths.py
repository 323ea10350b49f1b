"""Where mogaf keeps its cache (compiled kernels, converted LPIPS weights).

The workflow sets MOGAF_CACHE_DIR to `<workdir>/.cache/mogaf` (config key
`cache_dir`), so a pipeline run writes only under results/ and that folder.
Library users without the variable get ~/.cache/mogaf.
"""

from __future__ import annotations

import os
from pathlib import Path

ENV_CACHE = "MOGAF_CACHE_DIR"


def cache_dir(*parts: str, create: bool = True) -> Path:
    base = os.environ.get(ENV_CACHE) or os.path.join(os.path.expanduser("~"), ".cache", "mogaf")
    path = Path(base, *parts)
    if create:
        path.mkdir(parents=True, exist_ok=True)
    return path


def use_cache_dir(default: str | os.PathLike) -> Path:
    """Make `default` the cache folder unless MOGAF_CACHE_DIR is already set,
    and keep matplotlib's font cache in it too (it would go under ~/.cache).
    Called by the workflow, so that a run writes only under results/ and here."""
    if not os.environ.get(ENV_CACHE):
        os.environ[ENV_CACHE] = str(Path(default).resolve())
    base = Path(os.environ[ENV_CACHE])
    if not os.environ.get("MPLCONFIGDIR"):
        os.environ["MPLCONFIGDIR"] = str(base / "matplotlib")
    return base
