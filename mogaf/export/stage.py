"""The export stage: one method's forecast as 3DGS PLY files and index.json (run_export_stage)."""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..artefact import atomic_folder, open_artefact, read_dataset, write_json
from ..errors import MogafError, input_error
from ..evaluate.inputs import FORECAST_STAGE, _check_forecast, read_forecast
from ..representation import Model4D, load_model
from ..scene import Scene
from ..split import Split, load_frames, read_split
from .clouds import model_splats, posed_splats
from .params import ExportSettings, load_settings
from .ply import write_splat_ply

log = logging.getLogger(__name__)

FORMAT = "3dgs-ply"  # index.json's `format`: the files' layout (mogaf.export.ply)


def export_steps(forecast_steps: np.ndarray, chosen: list | None, forecast_h5: str | os.PathLike) -> np.ndarray:
    """The forecast time steps to write: `chosen` (export.steps) in time
    order, each one of the forecast's, or all of them for None."""
    steps = np.asarray(forecast_steps, np.int64)
    if chosen is None:
        return steps
    for step in chosen:
        if isinstance(step, bool) or not isinstance(step, (int, np.integer)) or step not in steps:
            raise MogafError(
                f"export param 'steps': {step!r} is not a forecast time step of {forecast_h5} "
                f"({int(steps.min())}..{int(steps.max())})"
            )
    return np.unique(np.asarray(chosen, np.int64))


def grid_time(step: int, num_timesteps: int) -> float:
    """Normalised time in [0, 1] of a step of the scene's uniform time grid."""
    return float(step) / (num_timesteps - 1) if num_timesteps > 1 else 0.0


def ply_name(kind: str, step: int) -> str:
    return f"{kind}_t{int(step):04d}.ply"


def step_cameras(frames: Scene, step: int) -> list[dict[str, Any]]:
    """The cameras of `frames` at time step `step`: OpenCV world-to-camera, K in pixels."""
    return [
        {
            "frame": frames.frame_names[f],
            "K": np.asarray(frames.K[f], np.float64).tolist(),
            "w2c": np.asarray(frames.w2c[f], np.float64).tolist(),
            "width": frames.width,
            "height": frames.height,
        }
        for f in np.flatnonzero(np.asarray(frames.time_index) == int(step))
    ]


def forecast_group_ids(forecast_h5: str | os.PathLike, num_gaussians: int) -> np.ndarray:
    """The motion group of every dynamic Gaussian, as the forecast recorded it."""
    with open_artefact(forecast_h5, FORECAST_STAGE) as fh:
        if "group_id" not in fh:
            raise input_error(forecast_h5, "has no entry 'group_id' (export.group_id needs it); rerun the forecast")
        ids = np.asarray(read_dataset(fh["group_id"], Path(forecast_h5), "group_id"), np.int64)
    if ids.shape != (num_gaussians,):
        raise input_error(forecast_h5, f"entry 'group_id' has shape {ids.shape}, expected ({num_gaussians},)")
    return ids


def _last_observed_position(model: Model4D, split: Split, model_h5: str | os.PathLike) -> tuple[int, int]:
    """(the split's last observed step, its index in the model's trajectories)."""
    step = int(split.observed_timesteps[-1])
    hits = np.flatnonzero(np.asarray(model.timesteps) == step)
    if hits.size == 0:
        raise input_error(model_h5, f"has no trajectory at the split's last observed time step {step}")
    return step, int(hits[0])


def _entry(kind: str, step: int, split: Split, frames: Scene, folder: str) -> dict[str, Any]:
    return {
        "file": f"{folder}/{ply_name(kind, step)}",
        "kind": kind,
        "timestep": int(step),
        "time": grid_time(step, split.num_timesteps),
        "cameras": step_cameras(frames, step),
    }


def run_export_stage(
    model_h5: str,
    forecast_h5: str,
    scene_h5: str,
    split_h5: str,
    out: str,
    params: Mapping[str, Any] | ExportSettings | None,
    *,
    ply_dir: str,
) -> Path:
    """Write the model at the last observed step (kind "observed") and the
    forecast at the chosen forecast steps (kind "forecast") as 3DGS PLY files
    into `ply_dir`, then `out` (index.json) listing them with their time step,
    time and the evaluation cameras at that step ("evaluation" frames; for the
    observed file the held-out "evaluation_observed" ones). Each file holds
    exactly the Gaussians the evaluation renders at that step."""
    p = load_settings(params)
    split = read_split(split_h5)
    model = load_model(model_h5)
    fc = read_forecast(forecast_h5)
    _check_forecast(fc, model, split)
    steps = export_steps(fc["timesteps"], p.steps, forecast_h5)
    last_step, last = _last_observed_position(model, split, model_h5)
    group_id = forecast_group_ids(forecast_h5, len(model.fg)) if p.group_id else None
    frames = {
        "observed": load_frames(scene_h5, split, "evaluation_observed"),
        "forecast": load_frames(scene_h5, split, "evaluation"),
    }
    splats = model_splats(model, quadrature_order=p.sh_fit_order, fg_group_id=group_id)
    # index.json names its files relative to itself: the folder pair can be moved whole
    folder = os.path.relpath(ply_dir, os.path.dirname(os.path.abspath(out))).replace(os.sep, "/")
    position = {int(t): i for i, t in enumerate(fc["timesteps"])}
    entries = [_entry("observed", last_step, split, frames["observed"], folder)]
    entries += [_entry("forecast", int(t), split, frames["forecast"], folder) for t in steps]
    with atomic_folder(ply_dir) as tmp:
        write_splat_ply(
            tmp / ply_name("observed", last_step),
            posed_splats(splats, model.trajectory_means[:, last], model.trajectory_quats[:, last]),
        )
        for t in steps:
            i = position[int(t)]
            write_splat_ply(tmp / ply_name("forecast", t), posed_splats(splats, fc["means"][:, i], fc["quats"][:, i]))
    index = {
        "format": FORMAT,
        "method": fc["attrs"].get("method"),
        "model": os.fspath(model_h5),
        "forecast": os.fspath(forecast_h5),
        "sh_degree": int(model.sh_degree),
        # degree 0 converts exactly; above it the colours are a least-squares fit (mogaf.export.colors)
        "sh_colors": "exact" if model.sh_degree == 0 else "fitted",
        "background": [float(c) for c in model.background],
        "num_gaussians": {"dynamic": len(model.fg), "background": len(splats) - len(model.fg)},
        "group_id": bool(p.group_id),
        "cameras": "OpenCV world-to-camera w2c (4x4), intrinsics K (3x3) in pixels",
        "files": entries,
    }
    log.info("export: %d PLY files of %d Gaussians in %s", len(entries), len(splats), ply_dir)
    return write_json(out, index)
