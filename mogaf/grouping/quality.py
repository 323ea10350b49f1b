"""Stage grouping_quality (-> grouping_quality.h5): the grouping's quality
against GT instance masks or segments at held-out views at observed times.

Its own stage, not part of evaluation, so that the ablations sharing one
grouping (forecast-only variants) render its held-out views once. It reads
the model that was grouped (recon.h5), groups.h5, the split and scene.h5's
"evaluation_observed" frames: held-out cameras, observed times only, with
their ground-truth segments where the scene has them (synthetic scenes,
masks shipped or not).

grouping_quality.h5 (stage "grouping_quality"):
  per_object_iou (M,) float64       IoU of each GT object present (mogaf.grouping.metrics)
  object_ids (M,) int64
  attrs: method, num_groups, params (JSON), quality (JSON: the section
    evaluation copies into metrics.json["grouping"] but for the two arrays
    above, which the reader puts back; only method and num_groups where there
    is nothing to compare: no GT instance masks, no held-out view at an
    observed step, or no group)
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..artefact import config_digest, open_artefact, read_artefact, write_artefact
from ..errors import input_error
from ..scene import SCENE_STAGE, load_segments
from ..settings import as_dict, defaults, load
from ..split import Split, evenly_spaced_frame_ids, load_evenly_spaced_frames, read_split
from .params import GroupingQualitySettings

GROUPING_QUALITY_STAGE = "grouping_quality"


DEFAULT_PARAMS: dict[str, Any] = defaults(GroupingQualitySettings)


def _settings(params: Mapping[str, Any] | GroupingQualitySettings | None) -> GroupingQualitySettings:
    return load(GroupingQualitySettings, "grouping_quality", params)


def measure_grouping_quality(
    grouped_model_h5: str | os.PathLike,
    groups_h5: str | os.PathLike,
    scene_h5: str | os.PathLike,
    split: Split,
    params: Mapping[str, Any] | GroupingQualitySettings | None = None,
) -> dict[str, Any]:
    """The grouping's method and size, and where the scene has GT instance
    masks and held-out views at observed times, its per-object IoU and ARI,
    rendered with the model that was grouped."""
    # local: reading a grouping_quality.h5 (evaluate, the report) needs neither torch nor scikit-learn
    from ..representation import load_model
    from .metrics import grouping_quality
    from .stage import load_groups

    p = _settings(params)
    groups = load_groups(groups_h5)
    out: dict[str, Any] = {"method": groups.method, "num_groups": groups.num_groups}
    ids = split.frame_ids.get("evaluation_observed", np.zeros(0, np.int64))
    with open_artefact(scene_h5, SCENE_STAGE) as fh:
        has_ground_truth = "frames/instance_mask" in fh or "segments" in fh
    if ids.size == 0 or groups.num_groups == 0 or not has_ground_truth:
        return out
    frames = load_evenly_spaced_frames(scene_h5, split, "evaluation_observed", int(p.max_frames))
    frames.segments = load_segments(scene_h5, evenly_spaced_frame_ids(split, "evaluation_observed", int(p.max_frames)))
    quality = grouping_quality(load_model(grouped_model_h5), groups, frames, alpha=float(p.alpha), pixels=str(p.pixels))
    return {**out, **quality}


def run_grouping_quality_stage(
    grouped_model_h5: str | os.PathLike,
    groups_h5: str | os.PathLike,
    scene_h5: str | os.PathLike,
    split_h5: str | os.PathLike,
    out: str | os.PathLike,
    params: Mapping[str, Any] | None = None,
) -> Path:
    p = _settings(params)
    quality = measure_grouping_quality(grouped_model_h5, groups_h5, scene_h5, read_split(split_h5), p)
    # The per-object arrays are entries; the section's other keys an attribute.
    arrays = {"per_object_iou": np.float64, "object_ids": np.int64}
    data = {key: np.asarray(quality.get(key, []), dtype) for key, dtype in arrays.items()}
    section = {k: v for k, v in quality.items() if k not in arrays}
    attrs = {
        "method": quality["method"],
        "num_groups": int(quality["num_groups"]),
        "params": as_dict(p),
        "quality": section,
    }
    return write_artefact(out, GROUPING_QUALITY_STAGE, data, config_digest=config_digest(as_dict(p)), attrs=attrs)


def read_grouping_quality(path: str | os.PathLike) -> dict[str, Any]:
    """The section metrics.json["grouping"] carries."""
    art = read_artefact(path, GROUPING_QUALITY_STAGE, required=("per_object_iou", "object_ids"))
    section = art.attrs["quality"]
    if not isinstance(section, dict) or "method" not in section or "num_groups" not in section:
        raise input_error(path, "attribute 'quality' is not a grouping-quality section (corrupted artefact)")
    quality = dict(section)
    names = quality.get("object_names", [])  # absent where nothing was measured
    for key, dtype in (("per_object_iou", np.float64), ("object_ids", np.int64)):
        values = np.asarray(art[key], dtype)
        if values.shape != (len(names),):
            raise input_error(
                path,
                f"entry '{key}' has shape {values.shape}, but 'quality' names {len(names)} "
                "object(s) (corrupted artefact)",
            )
        if "object_names" in quality:
            quality[key] = values.tolist()
    return quality
