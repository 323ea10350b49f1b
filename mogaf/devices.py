"""Which torch device a stage computes on (the config's top-level `device`)."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

from mogaf.errors import MogafError

DEVICE_CHOICES = ("auto", "cpu", "cuda")


def check_device_name(name: object, what: str) -> str:
    """The device setting itself, refused with one line when it is not a choice."""
    if not isinstance(name, str) or name not in DEVICE_CHOICES:
        raise MogafError(f"{what}: device must be one of {', '.join(DEVICE_CHOICES)}, got {name!r}")
    return name


def resolve_device(name: str, what: str):
    """'auto' -> CUDA when torch sees a CUDA device, else the CPU; 'cuda'
    without one is refused (never a silent fall-back to a slower device)."""
    import torch

    check_device_name(name, what)
    if name == "cuda" or (name == "auto" and torch.cuda.is_available()):
        if not torch.cuda.is_available():
            raise MogafError(f"{what}: device 'cuda' asked for, but torch sees no CUDA device")
        # cuBLAS is deterministic only with a fixed workspace, set before its first use
        # (a user's own setting wins); see torch.use_deterministic_algorithms.
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        return torch.device("cuda")
    return torch.device("cpu")


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Torch's intra-op thread count set to n inside, restored after (None: left alone)."""
    import torch

    before = torch.get_num_threads()
    if n is not None:
        torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(before)
