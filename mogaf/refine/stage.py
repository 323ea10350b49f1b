"""The refine stage: recon.h5 + groups.h5 (+ rigid.h5) -> refined.h5 (run_refine_stage)."""

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
from ..grouping.core import Groups
from ..grouping.stage import load_groups, read_rigid_init
from ..recon.checkpoint import run_resumable
from ..recon.data import TrainData, input_digests, load_train_data
from ..recon.init_common import InitResult
from ..recon.params import load_settings as load_recon_settings
from ..recon.stage import prepare_data
from ..recon.trainer import load_checkpoint
from ..representation import Model4D, load_model, save_model
from ..split import read_split
from .params import RefineSettings, resolve_params
from .trainer import RefineTrainer, rigid_residuals

log = logging.getLogger(__name__)

STAGE = "refine"


def _init_from_model(model: Model4D, data: TrainData) -> InitResult:
    fg = {k: torch.as_tensor(np.asarray(v, np.float32)) for k, v in model.fg.as_dict().items()}
    fg["motion_coef_logits"] = torch.as_tensor(np.asarray(model.motion_coef_logits, np.float32))
    bg = None
    if model.bg is not None:
        bg = {k: torch.as_tensor(np.asarray(v, np.float32)) for k, v in model.bg.as_dict().items()}
    canonical_step = int(model.attrs.get("canonical_timestep", data.timesteps[0]))
    pos = np.flatnonzero(data.timesteps[data.tidx] == canonical_step)
    return InitResult(
        fg=fg,
        rot6d=torch.as_tensor(np.asarray(model.rot6d, np.float32)),
        transl=torch.as_tensor(np.asarray(model.translations, np.float32)),
        bg=bg,
        scene_scale=float(model.scene_scale),
        canonical_frame=int(pos[0]) if pos.size else 0,
        motion_source="refine",
        info={},
    )


def _group_arrays(groups: Groups) -> dict[str, np.ndarray]:
    return {
        "group_id": np.asarray(groups.group_id, np.int64),
        "group_rigid": np.asarray(groups.rigid, np.int8),
        "group_static": np.asarray(groups.static, np.int8),
    }


def stage_digest(p: Mapping[str, Any], seed: int) -> str:
    return config_digest({"stage": STAGE, "params": dict(p), "seed": int(seed)})


def run_refine_stage(
    model_h5: str | os.PathLike,
    groups_h5: str | os.PathLike,
    rigid_h5: str | os.PathLike | None,
    priors_h5: str | os.PathLike | None,
    scene_h5: str | os.PathLike,
    split_h5: str | os.PathLike,
    out_h5: str | os.PathLike,
    params: Mapping[str, Any] | None = None,
    *,
    seed: int = 0,
    checkpoint: str | os.PathLike | None = None,
    progress: bool = True,
    keep_checkpoint: bool = False,
    stop_at: int | None = None,
) -> Path:
    """Refine recon.h5 group-wise and write refined.h5 (recon.h5's schema plus groups/).

    rigid_h5 may be None only when groups.h5 has no rigid group. checkpoint /
    stop_at: as in mogaf.recon.stage.run_recon_stage (resumable training state).
    """
    t_start = time.perf_counter()
    model = load_model(model_h5, ("recon",))
    groups = load_groups(groups_h5)
    N = len(model.fg)
    if groups.group_id.size != N:
        raise input_error(groups_h5, f"groups cover {groups.group_id.size} Gaussians, {model_h5} has {N}")
    p = resolve_params(params, model.attrs.get("params"))
    rp = p["recon"]  # the recon.h5 parameters with refine's overrides (a dict: recorded as it is)
    rs = load_recon_settings(rp)
    settings = RefineSettings(**p)
    has_rigid = bool(np.any((groups.rigid == 1) & (groups.static == 0)))
    rigid = None
    if has_rigid:
        if rigid_h5 is None:
            raise input_error(groups_h5, "has rigid groups but no rigid.h5 was given (run rigid_init first)")
        rigid = read_rigid_init(rigid_h5)
        Kr, T = rigid["rotations"].shape[:2]
        if model.timesteps.size != T or not np.array_equal(rigid.get("timesteps", model.timesteps), model.timesteps):
            raise input_error(rigid_h5, f"has {T} time steps, {model_h5} has {model.timesteps.size}")
        expect = np.flatnonzero(groups.rigid == 1)
        if not np.array_equal(np.sort(rigid["group_ids"]), expect):
            raise input_error(
                rigid_h5, f"covers groups {rigid['group_ids'].tolist()}, {groups_h5} has rigid groups {expect.tolist()}"
            )
    dynamic = np.flatnonzero(groups.static == 0)
    before = rigid_residuals(model, groups)
    attrs: dict[str, Any] = {
        "seed": int(seed),
        "params": {k: v for k, v in p.items() if k != "recon"},
        "recon_params": rp,
        "rigid_residual_before": before,
    }
    digest = stage_digest(p, seed)
    if dynamic.size == 0 or settings.iterations == 0 or N == 0:
        # nothing moves (or refinement switched off): the reconstruction as it is
        log.info(
            "refine: %s; refined.h5 = recon.h5 + group ids", "no dynamic group" if dynamic.size == 0 else "0 iterations"
        )
        model.groups = _group_arrays(groups)
        attrs.update(
            noop=1,
            iterations=0,
            wall_time_s=float(time.perf_counter() - t_start),
            rigid_residual_after=before,
            time_breakdown_s=None,  # recon's, inherited through model.attrs: not refine's
        )
        return save_model(out_h5, STAGE, model, config_digest=digest, attrs=attrs)

    with torch_threads(rs.threads if rs.threads > 0 else None):
        torch.manual_seed(int(seed))
        split = read_split(split_h5)
        data = load_train_data(scene_h5, split, priors_h5, downscale=rs.downscale)
        if not np.array_equal(data.timesteps, model.timesteps):
            raise input_error(model_h5, "its observed time steps differ from the split's")
        prepare_data(data, rp)
        inputs = input_digests(
            {
                "model": model_h5,
                "groups": groups_h5,
                "rigid": rigid_h5 if has_rigid else None,
                "scene": scene_h5,
                "split": split_h5,
                "priors": priors_h5,
            }
        )
        ck_digest = config_digest(
            {"stage": STAGE, "params": p, "seed": int(seed), "inputs": inputs, "frames": data.frame_ids.tolist()}
        )
        state = load_checkpoint(checkpoint, ck_digest) if checkpoint is not None else None
        init = None if state is not None else _init_from_model(model, data)
        trainer = RefineTrainer(data, rp, seed, groups, rigid, p, init=init, state=state)
        paused = run_resumable(
            trainer,
            log,
            stage="refine",
            resumed=state is not None,
            checkpoint=checkpoint,
            digest=ck_digest,
            progress=progress,
            stop_at=stop_at,
        )
        if paused is not None:
            return paused
        train_psnr = trainer.psnr_all()
        refined = trainer.model.to_model4d(model.timesteps, data.background, trainer.curve.as_arrays())
    if len(refined.fg) != N:
        raise MogafError(f"refine: the Gaussian count changed ({N} -> {len(refined.fg)}); group ids would not match")
    refined.groups = _group_arrays(groups)
    refined.attrs = {k: v for k, v in model.attrs.items() if k in ("canonical_timestep", "bases_init")}
    after = rigid_residuals(refined, groups)
    if "train_psnr" in model.attrs:
        attrs["train_psnr_recon"] = float(model.attrs["train_psnr"])
    attrs.update(
        noop=0,
        iterations=int(rs.iterations),
        train_psnr=float(train_psnr),
        wall_time_s=float(time.perf_counter() - t_start),
        rigid_residual_after=after,
        num_nr_pairs=int(sum(int(v.shape[0]) for v in trainer.pairs.values())),
        time_breakdown_s=trainer.time_breakdown(),
    )
    log.info("refine: rigid residual %s -> %s, train PSNR %.2f dB", before, after, train_psnr)
    path = save_model(out_h5, STAGE, refined, config_digest=digest, attrs=attrs)
    if checkpoint is not None and not keep_checkpoint:
        Path(checkpoint).unlink(missing_ok=True)
    return path
