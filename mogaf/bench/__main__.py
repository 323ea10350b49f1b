"""Dispatch `python -m mogaf.bench <name> ...` to mogaf.bench.<name>.main."""

from __future__ import annotations

import importlib
import pkgutil
import sys

import mogaf.bench as _pkg
from mogaf.allocator import keep_heap


def available() -> list[str]:
    return sorted(m.name for m in pkgutil.iter_modules(_pkg.__path__) if not m.name.startswith("_"))


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    names = available()
    if not argv or argv[0] in ("-h", "--help"):
        print("usage: python -m mogaf.bench {" + ",".join(names) + "} [options]")
        return 0 if argv else 2
    name, rest = argv[0], argv[1:]
    if name not in names:
        print(f"mogaf.bench: unknown benchmark '{name}' (choose from {', '.join(names)})", file=sys.stderr)
        return 2
    keep_heap()  # as in every stage's process, so the timings are the pipeline's (bench render sets its own)
    return int(importlib.import_module(f"mogaf.bench.{name}").main(rest) or 0)


if __name__ == "__main__":
    sys.exit(main())
