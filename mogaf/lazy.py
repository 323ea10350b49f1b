"""Lazy re-exports for a package's `__init__` (PEP 562).

A stage package's `__init__` re-exports its entry points, whose modules pull
in torch, OpenCV or scikit-learn. Importing the package only for its light
`params` module (the config schema and defaults do, at every workflow and
CLI start) must not load those: the names listed here are imported from their
module on first access, then cached in the package.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping
from typing import Any


def lazy_exports(package: str, exports: Mapping[str, str]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """(`__getattr__`, `__dir__`) for `package`, whose `exports` maps a name to
    the module (relative to the package, e.g. ".stage") that defines it."""

    def __getattr__(name: str) -> Any:
        if name not in exports:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(exports[name], package), name)
        setattr(sys.modules[package], name, value)  # later lookups skip this function
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(exports))

    return __getattr__, __dir__
