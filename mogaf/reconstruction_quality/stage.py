"""The reconstruction_quality stage: writing and reading reconstruction_quality/{model}.h5."""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..artefact import config_digest, read_artefact, write_artefact
from ..errors import input_error
from ..metrics import mean_metrics
from ..settings import as_dict
from ..split import read_split
from .params import RECONSTRUCTION_QUALITY_STAGE, load_settings


def run_reconstruction_quality_stage(
    model_h5: str | os.PathLike,
    scene_h5: str | os.PathLike,
    split_h5: str | os.PathLike,
    out: str | os.PathLike,
    params: Mapping[str, Any] | None = None,
) -> Path:
    from .measure import measure_reconstruction_quality  # local: torch; reading the artefact needs none

    p = load_settings(params)
    measured = measure_reconstruction_quality(model_h5, scene_h5, read_split(split_h5), p)
    data = {
        "frame_ids": measured["frame_ids"],
        "timesteps": measured["timesteps"],
        "camera_ids": measured["camera_ids"],
        "per_frame": per_frame_arrays(measured["per_frame"]),
    }
    attrs = {
        "params": as_dict(p),
        "heldout_observed": mean_metrics(measured["per_frame"]),
        "observed_motion": measured["observed_motion"],
    }
    return write_artefact(out, RECONSTRUCTION_QUALITY_STAGE, data, config_digest=config_digest(as_dict(p)), attrs=attrs)


def per_frame_arrays(per_frame: list[dict[str, float]]) -> dict[str, np.ndarray]:
    """Each metric every frame has, finite in every frame (a perfect render's
    PSNR is +inf: left out here, as in the mean), as one array over the frames."""
    if not per_frame:
        return {}
    common = set.intersection(*(set(d) for d in per_frame))
    arrays = {k: np.array([d[k] for d in per_frame], np.float64) for k in sorted(common)}
    return {k: v for k, v in arrays.items() if np.all(np.isfinite(v))}


def read_per_frame(path: str | os.PathLike) -> dict[str, Any]:
    """{"timesteps", "camera_ids", "per_frame": {metric: values}} of a
    reconstruction_quality artefact ("camera_ids": the held-out camera of each
    frame, None in an artefact written before they were recorded)."""
    art = read_artefact(path, RECONSTRUCTION_QUALITY_STAGE, required=("timesteps",))
    timesteps = np.asarray(art["timesteps"], np.int64)
    per_frame = {k: np.asarray(v, np.float64) for k, v in (art.get("per_frame") or {}).items()}
    camera_ids = np.asarray(art["camera_ids"], np.int64) if "camera_ids" in art else None
    for key, values in [*(("per_frame/" + k, v) for k, v in per_frame.items()), ("camera_ids", camera_ids)]:
        if values is not None and values.shape != timesteps.shape:
            raise input_error(path, f"entry '{key}' has shape {values.shape}, expected {timesteps.shape}")
    return {"timesteps": timesteps, "camera_ids": camera_ids, "per_frame": per_frame}


def read_reconstruction_quality(path: str | os.PathLike) -> dict[str, Any]:
    """The section metrics.json["reconstruction"] carries."""
    art = read_artefact(path, RECONSTRUCTION_QUALITY_STAGE, required=("frame_ids", "timesteps"))
    means = art.attrs.get("heldout_observed")
    if not isinstance(means, dict) or not all(isinstance(v, (int, float)) for v in means.values()):
        raise input_error(path, "attribute 'heldout_observed' is not a mapping of metric means (corrupted artefact)")
    num_frames = int(np.asarray(art["frame_ids"]).size)
    if np.asarray(art["timesteps"]).shape != (num_frames,):
        raise input_error(
            path,
            f"entry 'timesteps' has shape {np.asarray(art['timesteps']).shape}, "
            f"but {num_frames} frame(s) were rendered (corrupted artefact)",
        )
    motion = art.attrs.get("observed_motion", {})
    if not isinstance(motion, dict) or not all(isinstance(v, (int, float)) for v in motion.values()):
        raise input_error(path, "attribute 'observed_motion' is not a mapping of errors (corrupted artefact)")
    section: dict[str, Any] = {"observed_motion": {k: float(v) for k, v in motion.items()}} if motion else {}
    if num_frames == 0:
        return section
    return {"heldout_observed": {k: float(v) for k, v in means.items()}, "num_frames": num_frames, **section}
