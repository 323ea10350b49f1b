"""Image metrics of a 4D model rendered at held-out views at observed times."""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..metrics import image_metrics
from ..rendering import render_model
from ..representation import load_model
from ..split import Split, evenly_spaced_frame_ids, load_evenly_spaced_frames
from .params import load_settings


def measure_reconstruction_quality(
    model_h5: str | os.PathLike, scene_h5: str | os.PathLike, split: Split, params: Mapping[str, Any] | None = None
) -> dict[str, Any]:
    """Image metrics of the model rendered at held-out views at observed
    times: {"frame_ids", "timesteps", "per_frame"} (no frame when the split
    has none)."""
    p = load_settings(params)
    if split.frame_ids.get("evaluation_observed", np.zeros(0)).size == 0:
        return {"frame_ids": np.zeros(0, np.int64), "timesteps": np.zeros(0, np.int64), "per_frame": []}
    frame_ids = evenly_spaced_frame_ids(split, "evaluation_observed", int(p.max_frames))
    frames = load_evenly_spaced_frames(scene_h5, split, "evaluation_observed", int(p.max_frames))
    model = load_model(model_h5)
    masked = split.protocol == "iphone"
    masks = frames.covisibility_masks()
    per_frame = []
    for f in range(frames.num_frames):
        out = render_model(model, int(frames.time_index[f]), frames.K[f], frames.w2c[f], frames.width, frames.height)
        pred = np.clip(out.features[..., :3].detach().cpu().numpy().astype(np.float64), 0, 1)
        per_frame.append(
            image_metrics(pred, frames.images[f] / 255.0, None if masks is None else masks[f], masked, use_lpips=False)
        )
    return {"frame_ids": frame_ids, "timesteps": np.asarray(frames.time_index, np.int64), "per_frame": per_frame}
