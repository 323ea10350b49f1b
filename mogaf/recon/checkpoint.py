"""Training curve and checkpoint files of the reconstruction trainer.

A checkpoint (CHECKPOINT_VERSION, tagged with the run's config digest) is
written atomically by save_checkpoint and read back by load_checkpoint only
when its version and digest match; the Curve it carries is the logged loss,
PSNR and Gaussian count.
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..artefact import write_bytes

CHECKPOINT_VERSION = 1


@dataclass
class Curve:
    iteration: list[int] = field(default_factory=list)
    loss: list[float] = field(default_factory=list)
    psnr: list[float] = field(default_factory=list)
    num_gaussians: list[int] = field(default_factory=list)

    def as_arrays(self) -> dict[str, np.ndarray]:
        return {
            "iteration": np.asarray(self.iteration, dtype=np.int64),
            "loss": np.asarray(self.loss, dtype=np.float64),
            "psnr": np.asarray(self.psnr, dtype=np.float64),
            "num_gaussians": np.asarray(self.num_gaussians, dtype=np.int64),
        }


def save_checkpoint(path: str | os.PathLike, state: dict[str, Any]) -> None:
    """torch.save into memory, then one atomic write: torch's own file writer
    turns a full disk into a traceback about zip positions."""
    buffer = io.BytesIO()
    torch.save(state, buffer)
    write_bytes(path, buffer.getbuffer())


def load_checkpoint(path: str | os.PathLike, digest: str) -> dict[str, Any] | None:
    """The checkpoint's state if it exists, is readable and matches `digest`; else None."""
    p = Path(path)
    if not p.exists():
        return None
    try:
        state = torch.load(p, map_location="cpu", weights_only=True)
    except Exception:
        return None
    if not isinstance(state, dict) or state.get("version") != CHECKPOINT_VERSION or state.get("digest") != digest:
        return None
    return state


def run_resumable(
    trainer: Any,  # a recon.trainer.Trainer
    log,
    *,
    stage: str,
    resumed: bool,
    checkpoint: str | os.PathLike | None,
    digest: str,
    progress: bool,
    stop_at: int | None,
) -> Path | None:
    """Train to the end, or to `stop_at` leaving a checkpoint (its path is returned then; None at the end)."""
    if resumed:
        log.info(
            "%s: resumed from %s at iteration %d of %d", stage, checkpoint, trainer.iteration, trainer.p.iterations
        )
    trainer.run(progress=progress, checkpoint=checkpoint, digest=digest, stop_at=stop_at, stage=stage)
    if stop_at is not None and trainer.iteration < trainer.p.iterations:
        if checkpoint is None:
            raise ValueError("stop_at needs a checkpoint path")
        save_checkpoint(checkpoint, trainer.checkpoint_state(digest))
        return Path(checkpoint)
    return None
