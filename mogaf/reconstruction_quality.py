"""Stage reconstruction_quality (-> reconstruction_quality/{refined,recon}.h5):
the 4D model's image quality at held-out views at observed times.

Its own stage, not part of evaluation, so that the variants forecasting from
one model (e.g. every forecaster ablation) render these views once. It reads
the model the forecasts start from (refined.h5, or recon.h5 without
refinement), the split and scene.h5's "evaluation_observed" frames: held-out
cameras, observed times only, so no future frame is opened.

reconstruction_quality/{model}.h5 (stage "reconstruction_quality"):
  frame_ids (F,) int64     scene frames rendered (evenly spaced, at most max_frames)
  timesteps (F,) int64     their time steps
  attrs: params (JSON), heldout_observed (JSON: mean PSNR and SSIM, and for
    the iPhone protocol mPSNR and mSSIM over the co-visible pixels; a frame
    whose value is not finite, e.g. a perfect render, is left out of a mean)
metrics.json["reconstruction"] copies it: {"heldout_observed": ..., "num_frames": F},
or {} where the split has no held-out view at an observed step.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .artefact import config_digest, read_artefact, write_artefact
from .errors import input_error, refuse_unknown_params
from .metrics import image_metrics, mean_metrics
from .representation import load_model
from .rendering import render_model
from .split import Split, evenly_spaced_frame_ids, load_evenly_spaced_frames, read_split

RECONSTRUCTION_QUALITY_STAGE = "reconstruction_quality"
DEFAULT_PARAMS: dict[str, Any] = {
    "max_frames": 24,  # held-out views at observed times rendered (evenly spaced); 0 = all
}


def _resolve(params: Mapping[str, Any] | None) -> dict[str, Any]:
    refuse_unknown_params(RECONSTRUCTION_QUALITY_STAGE, params, DEFAULT_PARAMS)
    return {**DEFAULT_PARAMS, **dict(params or {})}


def measure_reconstruction_quality(model_h5: str | os.PathLike, scene_h5: str | os.PathLike, split: Split,
                                   params: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Image metrics of the model rendered at held-out views at observed
    times: {"frame_ids", "timesteps", "per_frame"} (no frame when the split
    has none)."""
    p = _resolve(params)
    if split.frame_ids.get("evaluation_observed", np.zeros(0)).size == 0:
        return {"frame_ids": np.zeros(0, np.int64), "timesteps": np.zeros(0, np.int64), "per_frame": []}
    frame_ids = evenly_spaced_frame_ids(split, "evaluation_observed", int(p["max_frames"]))
    frames = load_evenly_spaced_frames(scene_h5, split, "evaluation_observed", int(p["max_frames"]))
    model = load_model(model_h5)
    masked = split.protocol == "iphone"
    masks = frames.covisibility_masks()
    per_frame = []
    for f in range(frames.num_frames):
        out = render_model(model, int(frames.time_index[f]), frames.K[f], frames.w2c[f], frames.width, frames.height)
        pred = np.clip(out.features[..., :3].detach().cpu().numpy().astype(np.float64), 0, 1)
        per_frame.append(image_metrics(pred, frames.images[f] / 255.0, None if masks is None else masks[f], masked,
                                       use_lpips=False))
    return {"frame_ids": frame_ids, "timesteps": np.asarray(frames.time_index, np.int64), "per_frame": per_frame}


def run_reconstruction_quality_stage(model_h5: str | os.PathLike, scene_h5: str | os.PathLike,
                                     split_h5: str | os.PathLike, out: str | os.PathLike,
                                     params: Mapping[str, Any] | None = None) -> Path:
    p = _resolve(params)
    measured = measure_reconstruction_quality(model_h5, scene_h5, read_split(split_h5), p)
    data = {"frame_ids": measured["frame_ids"], "timesteps": measured["timesteps"]}
    attrs = {"params": p, "heldout_observed": mean_metrics(measured["per_frame"])}
    return write_artefact(out, RECONSTRUCTION_QUALITY_STAGE, data, config_digest=config_digest(p), attrs=attrs)


def read_reconstruction_quality(path: str | os.PathLike) -> dict[str, Any]:
    """The section metrics.json["reconstruction"] carries."""
    art = read_artefact(path, RECONSTRUCTION_QUALITY_STAGE, required=("frame_ids", "timesteps"))
    means = art.attrs.get("heldout_observed")
    if not isinstance(means, dict) or not all(isinstance(v, (int, float)) for v in means.values()):
        raise input_error(path, "attribute 'heldout_observed' is not a mapping of metric means (corrupted artefact)")
    num_frames = int(np.asarray(art["frame_ids"]).size)
    if np.asarray(art["timesteps"]).shape != (num_frames,):
        raise input_error(path, f"entry 'timesteps' has shape {np.asarray(art['timesteps']).shape}, "
                                f"but {num_frames} frame(s) were rendered (corrupted artefact)")
    if num_frames == 0:
        return {}
    return {"heldout_observed": {k: float(v) for k, v in means.items()}, "num_frames": num_frames}
