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
