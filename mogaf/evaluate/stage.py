"""The evaluation stage: metrics.json and renders of every forecast (run_evaluate_stage).

See the mogaf.evaluate package docstring for what is measured.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..artefact import atomic_folder, write_json
from ..cores import cores, shared_by
from ..grouping.quality import read_grouping_quality
from ..metrics import image_metrics, mean_metrics, metrics_left_out
from ..metrics.lpips import load_lpips_weights
from ..reconstruction_quality.stage import read_reconstruction_quality
from ..report.tables import METHOD_ORDER, method_label
from ..representation import load_model
from ..split import load_frames, read_split
from ..video import colour_legend, enlarge, enlargement, error_panel, labelled_row, text_scale, to_uint8
from .images import _save_png, render_forecast_views, video_encoder
from .inputs import _check_forecast, forecast_summary, read_forecast, runtime_section
from .params import load_settings
from .tracking import tracking_section

log = logging.getLogger(__name__)


def _round(obj: Any, digits: int = 6) -> Any:
    if isinstance(obj, float):
        return round(obj, digits) if math.isfinite(obj) else None
    if isinstance(obj, dict):
        # settings are copied as they are (an Adam eps of 1e-15 must not become 0)
        return {k: (v if k == "params" else _round(v, digits)) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_round(v, digits) for v in obj]
    if isinstance(obj, (np.floating,)):
        return _round(float(obj), digits)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    return obj


def run_evaluate_stage(
    *,
    scene: str,
    split: str,
    model: str,
    reconstruction_quality: str,
    grouping_quality: str,
    forecasts: Mapping[str, str],
    benchmarks: Mapping[str, str],
    out_metrics: str,
    out_renders: str,
    params: Mapping[str, Any],
    variant: str,
    ids: Mapping[str, str],
) -> Path:
    """metrics.json and renders of every forecast. `model`: the model the
    forecasts start from (refined.h5, or recon.h5 without refinement);
    `reconstruction_quality`: reconstruction_quality/{refined,recon}.h5 of that model;
    `grouping_quality`: grouping_quality.h5 of the grouping the forecasts used."""
    p = load_settings(params)
    start = time.perf_counter()
    cores()  # the idle cores are measured from here to the first forecast
    if p.lpips:
        load_lpips_weights()  # fail before rendering anything when the weights are missing
    # the sections copied from their own stages: a bad file fails before any render
    reconstruction = read_reconstruction_quality(reconstruction_quality)
    grouping = read_grouping_quality(grouping_quality)
    sp = read_split(split)
    m4 = load_model(model)
    frames = load_frames(scene, sp, "evaluation")
    masked = sp.protocol == "iphone"
    masks = frames.covisibility_masks()
    methods = sorted(forecasts)
    gts = [frames.images[f] / 255.0 for f in range(frames.num_frames)]
    result: dict[str, Any] = {
        "mogaf_version": __version__,
        "dataset": ids.get("dataset"),
        "scene": ids.get("scene"),
        "ratio": sp.ratio,
        "variant": variant,
        "protocol": sp.protocol,
        "num_evaluation_views": int(frames.num_frames),
        "forecast_timesteps": [int(t) for t in sp.forecast_timesteps],
        "methods": {},
    }
    left_out = metrics_left_out(frames.height, frames.width, bool(p.lpips))
    for metric, why in left_out.items():
        log.warning("%s: %s: %s is left out of the metrics", scene, why, metric.upper())
    if left_out:
        result["metrics_left_out"] = left_out
    if masked and masks is None:
        # DyCheck's masked metrics need its co-visibility masks: without them they equal the plain ones
        log.warning("%s: the scene has no co-visibility masks: mPSNR, mSSIM and mLPIPS are over every pixel", scene)
        result["masked_metrics_over"] = "every pixel: the scene has no co-visibility masks"
    labels: dict[str, str] = {}
    side_by_side: dict[str, list[np.ndarray]] = {}  # uint8 renders for all_methods.mp4
    factor = enlargement(frames.width, int(p.video_min_width))
    gt_tiles = [to_uint8(g) for g in gts]
    legend = colour_legend(frames.width * factor, p.video_error_max, text_scale(frames.width * factor))
    # renders and videos go to a temporary folder that replaces out_renders when complete
    with atomic_folder(out_renders) as renders_tmp, video_encoder() as write_video:

        def measure(method: str) -> tuple[dict[str, Any], str | None, list[np.ndarray] | None]:
            """The method's metrics section, its label and its tiles for all_methods.mp4 (videos on)."""
            label = tiles = None
            fc = read_forecast(forecasts[method])
            _check_forecast(fc, m4, sp)
            renders = render_forecast_views(m4, fc, frames, p)
            per = [
                image_metrics(renders[f], gts[f], None if masks is None else masks[f], masked, bool(p.lpips))
                for f in range(frames.num_frames)
            ]
            section: dict[str, Any] = {
                "image": mean_metrics(per),
                "per_view": [
                    {"frame": frames.frame_names[f], "timestep": int(frames.time_index[f]), **per[f]}
                    for f in range(frames.num_frames)
                ],
            }
            section["tracking"], quick = tracking_section(m4, fc, scene, sp, p)
            section["forecast"] = {**forecast_summary(fc["attrs"]), **(quick or {})}
            if p.save_renders:
                for f in range(frames.num_frames):
                    _save_png(renders_tmp / method / f"{frames.frame_names[f]}.png", renders[f])
            if p.video:
                label = method_label({"methods": {method: section}}, method)
                panels = [
                    labelled_row(
                        [enlarge(gt_tiles[f], factor), enlarge(to_uint8(renders[f]), factor)]
                        + [enlarge(error_panel(renders[f], gts[f], p.video_error_max), factor)],
                        ["GT", label, "|error|"],
                        f"{label}, time step {int(frames.time_index[f])}, view {frames.frame_names[f]}",
                        footers=[None, None, legend],
                    )
                    for f in range(frames.num_frames)
                ]
                write_video(renders_tmp / f"{method}.mp4", panels, int(p.video_fps))
                tiles = [enlarge(to_uint8(r), factor) for r in renders]
            return section, label, tiles

        # Forecasts are measured side by side where cores are idle (the same
        # values in any order); metrics.json lists them in the same order. Two
        # at most: each holds its renders and video panels in memory.
        workers = max(1, min(len(methods), cores(), 2))
        if workers > 1:
            log.info("measuring %d forecasts at a time on idle cores", workers)
        with shared_by(workers), ThreadPoolExecutor(max_workers=workers) as pool:
            measured = list(pool.map(measure, methods))
        for method, (section, label, tiles) in zip(methods, measured):
            result["methods"][method] = section
            if label is not None:
                labels[method] = label
                side_by_side[method] = tiles
        if p.video and len(methods) > 1:
            # one video of every method beside the GT, in the tables' order
            order = sorted(methods, key=lambda m: METHOD_ORDER.index(m) if m in METHOD_ORDER else len(METHOD_ORDER))
            panels = [
                labelled_row(
                    [enlarge(gt_tiles[f], factor)] + [side_by_side[m][f] for m in order],
                    ["GT"] + [labels[m] for m in order],
                    f"time step {int(frames.time_index[f])}, view {frames.frame_names[f]}",
                )
                for f in range(frames.num_frames)
            ]
            write_video(renders_tmp / "all_methods.mp4", panels, int(p.video_fps))
        result["reconstruction"] = reconstruction
        result["grouping"] = grouping
        if p.runtime_in_metrics:
            rt = runtime_section(benchmarks, methods)
            rt["stages"]["evaluate"] = {"wall_s": round(time.perf_counter() - start, 3), "max_rss_mb": None}
            result["runtime"] = rt
            for method in methods:
                result["methods"][method]["runtime"] = {"total_wall_s": rt["total_wall_s"][method]}
    return write_json(out_metrics, _round(result))
