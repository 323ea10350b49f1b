"""torch's Adam and deterministic-kernel switch, without importing torch's compiler.

torch.optim.Optimizer wraps add_param_group, zero_grad, state_dict and
load_state_dict in `torch._disable_dynamo`, and Adam.step in a helper that
imports torch._dynamo; torch.use_deterministic_algorithms imports
torch._inductor's config. Whichever runs first pulls in torch._dynamo and
torch._inductor: about a second of every stage process, for a compiler the
pipeline never uses. `Adam` runs torch's own undecorated functions (the same
arithmetic, bit for bit: tests/test_optim.py compares it with
torch.optim.Adam), and `use_deterministic_algorithms` sets only the flag that
eager kernels read.
"""

from __future__ import annotations

import inspect
import sys

import torch


class Adam(torch.optim.Adam):
    """torch.optim.Adam whose methods skip the decorators that import torch._dynamo
    (inspect.unwrap: the functions torch's decorators wrapped, whatever wrapped
    them since, e.g. the profiling hook of an Adam made before this class)."""

    add_param_group = inspect.unwrap(torch.optim.Optimizer.add_param_group)
    zero_grad = inspect.unwrap(torch.optim.Optimizer.zero_grad)
    state_dict = inspect.unwrap(torch.optim.Optimizer.state_dict)
    load_state_dict = inspect.unwrap(torch.optim.Optimizer.load_state_dict)
    _step = inspect.unwrap(torch.optim.Adam.step)

    def step(self, closure=None):
        # the decorator's one other effect: the update runs without autograd
        # (torch enables it only for a `differentiable` optimiser, never used here)
        with torch.no_grad():
            return self._step(closure)


def use_deterministic_algorithms(mode: bool, *, warn_only: bool = False) -> None:
    """torch.use_deterministic_algorithms for eager kernels. torch's own
    function also sets torch._inductor.config.deterministic, which only
    torch.compile reads; it is set too where that module is loaded already."""
    setter = getattr(torch._C, "_set_deterministic_algorithms", None)
    if setter is None or "torch._inductor.config" in sys.modules:
        torch.use_deterministic_algorithms(mode, warn_only=warn_only)
        return
    setter(mode, warn_only=warn_only)
