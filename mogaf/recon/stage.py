"""The reconstruction stage: scene.h5 + split.h5 + priors.h5 -> recon.h5."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..artefact import config_digest
from ..devices import torch_threads
from ..errors import MogafError, input_error
from ..representation import save_model
from ..split import read_split
from .checkpoint import run_resumable
from .data import TrainData, coarser, extend_masks_to_content, input_digests, load_train_data
from .init import initialise
from .init_common import _use_bg
from .params import load_settings, resolve_params
from .trainer import Trainer, load_checkpoint

log = logging.getLogger(__name__)

MOTION_AT_UNOBSERVED_STEPS = (
    "bases are stored at every observed time step; steps without a training frame are set, after "
    "every optimiser step, to the natural cubic spline through the steps that have one (the end "
    "value outside them); with gap_interpolation off they are left to the basis smoothness prior"
)


def stage_digest(params: Mapping[str, Any], seed: int) -> str:
    """Config digest written into recon.h5 (parameters + seed)."""
    return config_digest({"stage": "recon", "params": dict(params), "seed": int(seed)})


def checkpoint_digest(params: Mapping[str, Any], seed: int, data: TrainData, inputs: dict[str, str]) -> str:
    return config_digest(
        {
            "stage": "recon",
            "params": dict(params),
            "seed": int(seed),
            "inputs": inputs,
            "frames": data.frame_ids.tolist(),
            "shape": [data.num_frames, data.height, data.width],
        }
    )


def prepare_data(data: TrainData, p: dict) -> None:
    """Mask handling that depends on the parameters (see extend_masks_to_content)."""
    p = load_settings(p)
    if not _use_bg(p, data) and p.content_threshold > 0:
        extend_masks_to_content(data, p.content_threshold)


def build_trainer(
    data: TrainData, params: dict, seed: int, *, checkpoint: str | os.PathLike | None = None, digest: str = ""
) -> tuple[Trainer, bool]:
    """A Trainer resumed from `checkpoint` when its digest matches, else freshly initialised."""
    torch.manual_seed(int(seed))
    coarse = None
    s = load_settings(params)
    if s.coarse_downscale > 1 and s.coarse_fraction > 0:
        c = s.coarse_downscale
        if data.height // c >= 8 and data.width // c >= 8:
            coarse = coarser(data, c)
    state = load_checkpoint(checkpoint, digest) if checkpoint is not None else None
    if state is not None:
        return Trainer(data, params, seed, state=state, coarse=coarse), True
    t0 = time.perf_counter()
    init = initialise(coarse if coarse is not None else data, params, seed)
    init.info["init_time_s"] = time.perf_counter() - t0
    return Trainer(data, params, seed, init=init, coarse=coarse), False


def run_recon_stage(
    scene_h5: str | os.PathLike,
    split_h5: str | os.PathLike,
    priors_h5: str | os.PathLike | None,
    out_h5: str | os.PathLike,
    params: Mapping[str, Any] | None = None,
    *,
    seed: int = 0,
    checkpoint: str | os.PathLike | None = None,
    progress: bool = True,
    keep_checkpoint: bool = False,
    stop_at: int | None = None,
) -> Path:
    """Reconstruct the observed part of a scene as 4D Gaussians and write recon.h5.

    checkpoint: a path for the resumable training state (written atomically
    every `checkpoint_every` iterations; on start, resumed when its digest
    matches the parameters, seed and inputs, else ignored and overwritten);
    removed after success unless keep_checkpoint. stop_at: stop after that
    many iterations without writing recon.h5 (for tests of resumption);
    returns the checkpoint path then.
    """
    p = resolve_params(params)
    threads = load_settings(p).threads
    with torch_threads(threads if threads > 0 else None):
        return _run(scene_h5, split_h5, priors_h5, out_h5, p, seed, checkpoint, progress, keep_checkpoint, stop_at)


def _run(
    scene_h5,
    split_h5,
    priors_h5,
    out_h5,
    p: dict,
    seed: int,
    checkpoint,
    progress: bool,
    keep_checkpoint: bool,
    stop_at: int | None,
) -> Path:
    split = read_split(split_h5)
    s = load_settings(p)  # p: the resolved dict, recorded and hashed as it is
    data = load_train_data(scene_h5, split, priors_h5, downscale=s.downscale)
    prepare_data(data, p)
    inputs = input_digests({"scene": scene_h5, "split": split_h5, "priors": priors_h5})
    digest = checkpoint_digest(p, seed, data, inputs)
    try:
        trainer, resumed = build_trainer(data, p, seed, checkpoint=checkpoint, digest=digest)
    except MogafError as exc:
        if not str(exc).startswith("reconstruction init:"):
            raise
        empty = "; every foreground mask of its observed frames is empty" if not np.any(data.fg_masks) else ""
        raise input_error(scene_h5, f"{exc}{empty}") from None
    paused = run_resumable(
        trainer,
        log,
        stage="recon",
        resumed=resumed,
        checkpoint=checkpoint,
        digest=digest,
        progress=progress,
        stop_at=stop_at,
    )
    if paused is not None:
        return paused
    t0 = time.perf_counter()
    train_psnr = trainer.psnr_all()
    model = trainer.model.to_model4d(split.observed_timesteps, data.background, trainer.curve.as_arrays())
    wall = trainer.elapsed + float(trainer.init_info.get("init_time_s", 0.0)) + time.perf_counter() - t0
    info = trainer.init_info
    attrs = {
        "wall_time_s": float(wall),
        "train_psnr": float(train_psnr),
        "iterations": int(s.iterations),
        "seed": int(seed),
        "downscale": int(s.downscale),
        "train_width": data.width,
        "train_height": data.height,
        "num_fg": trainer.model.num_fg,
        "num_bg": trainer.model.num_bg,
        "canonical_timestep": int(split.observed_timesteps[data.tidx[trainer.canonical_frame]]),
        "bases_init": trainer.motion_source,
        "motion_at_unobserved_steps": MOTION_AT_UNOBSERVED_STEPS,
        # this process's share only, when resumed from a checkpoint
        "time_breakdown_s": {
            "init": round(float(trainer.init_info.get("init_time_s", 0.0)), 3) if not resumed else 0.0,
            **trainer.time_breakdown(),
            "training_psnr_and_model": round(time.perf_counter() - t0, 3),
        },
        "init": {
            k: (float(v) if isinstance(v, (float, np.floating)) else int(v))
            for k, v in info.items()
            if isinstance(v, (int, float, np.integer, np.floating))
        },
        "params": p,
    }
    path = save_model(out_h5, "recon", model, config_digest=stage_digest(p, seed), attrs=attrs)
    if checkpoint is not None and not keep_checkpoint:
        Path(checkpoint).unlink(missing_ok=True)
    return path
