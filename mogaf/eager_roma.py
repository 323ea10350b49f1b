"""roma, imported for eager use without loading torch's compiler.

At import, roma wraps two of its autograd functions in `torch._dynamo.disable`,
which keeps torch.compile from tracing them. That attribute access imports
torch._dynamo (about 1.3 s of every process that reaches roma: recon,
refine, a rigid group's forecast), for a compiler the pipeline
never runs. Outside torch.compile the wrapper only switches tracing off
around the call, so roma's functions compute the same thing, bit for bit,
without it (tests/test_optim.py compares them with a plain `import roma`).

`load()` imports roma with a stand-in whose `disable` returns the function it
is given. A roma that asks torch._dynamo for anything else at import gets a
plain import instead, compiler and all.
"""

from __future__ import annotations

import sys
import threading
import types
from typing import Any


def _unwrapped(fn: Any = None, recursive: bool = True, **_: Any) -> Any:
    if fn is None:  # used as @disable(recursive=...)
        return lambda f: f
    return fn


_lock = threading.Lock()


def load() -> types.ModuleType:
    """The roma module (imported on first use; one thread imports it)."""
    with _lock:
        return _load()


def _load() -> types.ModuleType:
    if "roma" in sys.modules:
        return sys.modules["roma"]
    import torch

    if "torch._dynamo" not in sys.modules:
        # a module attribute is found before torch's lazy __getattr__ would import the compiler
        stand_in = types.SimpleNamespace(disable=_unwrapped)
        torch._dynamo = stand_in
        try:
            import roma

            return roma
        except AttributeError:  # roma wants more of the compiler: the plain import below
            for name in [m for m in sys.modules if m == "roma" or m.startswith("roma.")]:
                del sys.modules[name]
        finally:
            if vars(torch).get("_dynamo") is stand_in:
                del torch._dynamo
    import roma

    return roma
