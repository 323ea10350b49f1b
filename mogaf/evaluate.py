"""Evaluation stage: render forecasts at the evaluation views and measure them.

For each enabled method it renders the forecast poses of the dynamic
Gaussians plus the static background at every evaluation view (held-out
cameras at forecast times), writes PNGs and a GT | forecast | error video,
and computes
- image metrics: PSNR, SSIM (11-px Gaussian window, sigma 1.5), LPIPS (AlexNet);
  for the iPhone protocol also mPSNR, mSSIM, mLPIPS with the covisibility
  masks when the dataset has them (DyCheck's protocol);
- tracking metrics where ground-truth tracks exist (synthetic scenes): GT
  surface points are attached to their nearest Gaussians at the last
  observed step (in each Gaussian's local frame) and carried by the
  forecast poses; 3D EPE, delta_3D, and on the train camera 2D AJ,
  delta_avg and occlusion accuracy (visibility from the rendered depth).
metrics.json also carries the model's quality at held-out views at observed
times (copied from reconstruction_quality/{refined,recon}.h5,
mogaf.reconstruction_quality),
the grouping quality (copied from grouping_quality.h5,
mogaf.grouping.quality), and the wall time and peak memory of
every stage that produced each method's result (Snakemake benchmark files).
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from . import __version__
from .artefact import read_artefact, write_json
from .errors import input_error, refuse_unknown_params
from .grouping.quality import read_grouping_quality
from .metrics import image_metrics, mean_metrics
from .representation import Model4D, load_model
from .rendering import render_poses
from .reconstruction_quality import read_reconstruction_quality
from .report.tables import METHOD_ORDER, method_label
from .video import labelled_row, to_uint8
from .split import Split, load_frames, load_ground_truth, read_split

log = logging.getLogger(__name__)

FORECAST_STAGE = "forecast"
DEFAULT_PARAMS: dict[str, Any] = {
    "lpips": True,                       # AlexNet LPIPS (paper Tables 1-2)
    "save_renders": True,                # PNG per evaluation view and method
    "video": True,                       # GT | forecast | error video per method
    "video_fps": 8,
    "tracking_neighbors": 4,             # Gaussians a GT point is attached to
    "tracking_scale": 1.0,               # scene units -> metres for delta_3D (SoM evaluates in metres)
    "aj_thresholds": [4, 8, 16, 32, 64],     # px; SoM's evaluation (paper follows SoM's protocol)
    "delta_thresholds": [4, 8, 16, 32, 64],  # px, issue/SoM delta_avg
    "visibility_tolerance": 0.03,        # relative depth slack for predicted visibility
    "runtime_in_metrics": True,          # wall time / memory in metrics.json (off: byte-identical reruns)
}


# ------------------------------------------------------------------ inputs
def read_forecast(path: str | os.PathLike) -> dict[str, Any]:
    art = read_artefact(path, FORECAST_STAGE, required=["timesteps", "means", "quats"])
    return {"timesteps": np.asarray(art["timesteps"], np.int64), "means": art["means"], "quats": art["quats"],
            "attrs": art.attrs, "path": str(path)}


def _check_forecast(fc: dict[str, Any], model: Model4D, split: Split) -> None:
    n = len(model.fg)
    if fc["means"].shape[:1] != (n,) or fc["quats"].shape[:1] != (n,):
        raise input_error(fc["path"], f"forecast has {fc['means'].shape[0]} Gaussians, the model has {n}")
    if not np.array_equal(fc["timesteps"], split.forecast_timesteps):
        raise input_error(fc["path"], "forecast time steps differ from the split's forecast time steps")


def read_benchmark(path: str | os.PathLike) -> dict[str, float]:
    """Wall seconds and peak RSS (MB) from a Snakemake benchmark TSV."""
    import pandas as pd

    p = Path(path)
    try:
        df = pd.read_csv(p, sep="\t")
    except (OSError, ValueError) as exc:
        raise input_error(p, f"not a readable benchmark TSV ({exc.__class__.__name__})") from None
    if "s" not in df.columns or df.empty:
        raise input_error(p, "benchmark TSV lacks the 's' column")
    wall = float(pd.to_numeric(df["s"], errors="coerce").fillna(0).sum())
    rss = pd.to_numeric(df.get("max_rss", pd.Series([np.nan])), errors="coerce").max()
    return {"wall_s": round(wall, 3), "max_rss_mb": None if not np.isfinite(rss) else round(float(rss), 1)}


# ------------------------------------------------------------------ images
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


def _save_png(path: Path, img: np.ndarray) -> None:
    import imageio.v3 as iio

    from .datasets.images import to_uint8

    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, to_uint8(np.asarray(img) * 255.0))


def _write_video(path: Path, panels: list[np.ndarray], fps: int) -> None:
    """uint8 frames (mogaf.video.labelled_row) as mp4 (gif when ffmpeg is unavailable)."""
    import imageio.v2 as iio2

    frames = []
    for img in panels:
        h, w = img.shape[:2]
        img = np.pad(img, ((0, h % 2), (0, w % 2), (0, 0)))  # even sizes for yuv420p
        frames.append(img)
    try:
        with iio2.get_writer(path, fps=fps, codec="libx264", quality=8, macro_block_size=2, ffmpeg_log_level="error") as writer:
            for f in frames:
                writer.append_data(f)
    except (ImportError, RuntimeError, OSError):
        gif = path.with_suffix(".gif")
        iio2.mimsave(gif, frames, duration=1.0 / max(fps, 1))


def render_forecast_views(model: Model4D, fc: dict[str, Any], frames, params: Mapping[str, Any]) -> list[np.ndarray]:
    index = {int(t): i for i, t in enumerate(fc["timesteps"])}
    renders = []
    for f in range(frames.num_frames):
        i = index[int(frames.time_index[f])]
        out = render_poses(model, fc["means"][:, i], fc["quats"][:, i], frames.K[f], frames.w2c[f], frames.width, frames.height)
        renders.append(np.clip(out.features[..., :3].detach().cpu().numpy().astype(np.float64), 0.0, 1.0))
    return renders


def forecast_summary(attrs: Mapping[str, Any]) -> dict[str, Any]:
    """What metrics.json keeps of a forecast artefact: no wall-clock values
    (they live in the runtime section), so reruns give identical files."""
    out = {k: attrs[k] for k in ("method", "groupwise", "num_groups_trained", "params", "coherence") if k in attrs}
    jobs = attrs.get("flags") or {}
    out["jobs"] = {job: {k: v for k, v in (info or {}).items() if not k.endswith("_time_s")} for job, info in sorted(jobs.items())}
    return out


# ------------------------------------------------------------------ tracking
def attach_points(points: np.ndarray, means: np.ndarray, quats: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Attach points (P,3) to their k nearest Gaussians at one time.

    Returns neighbour ids (P,k), inverse-distance weights (P,k) summing to 1,
    and each point's offset in each neighbour's local frame (P,k,3).
    """
    from scipy.spatial import cKDTree

    from .representation import quat_to_matrix
    import torch

    k = max(1, min(int(k), means.shape[0]))
    dist, idx = cKDTree(means).query(points, k=k)
    dist = dist.reshape(len(points), k)
    idx = idx.reshape(len(points), k)
    w = 1.0 / np.maximum(dist, 1e-9)
    w /= w.sum(axis=1, keepdims=True)
    R = quat_to_matrix(torch.as_tensor(quats, dtype=torch.float64)).numpy()  # (N,3,3)
    rel = points[:, None, :] - means[idx]
    offsets = np.einsum("pkji,pkj->pki", R[idx], rel)  # R^T (p - mu)
    return idx, w, offsets


def carry_points(idx: np.ndarray, weights: np.ndarray, offsets: np.ndarray, means: np.ndarray, quats: np.ndarray) -> np.ndarray:
    """Positions (P,T,3) of attached points under per-Gaussian poses (N,T,3/4)."""
    import torch

    from .representation import quat_to_matrix

    R = quat_to_matrix(torch.as_tensor(quats[idx], dtype=torch.float64)).numpy()  # (P,k,T,3,3)
    pos = np.einsum("pktij,pkj->pkti", R, offsets) + means[idx]  # (P,k,T,3)
    return np.einsum("pk,pkti->pti", weights, pos)


def predicted_gt_tracks(model: Model4D, fc: dict[str, Any], gt_observed: Mapping[str, Any], k: int) -> np.ndarray:
    """Forecast positions (P, T_fc, 3) of the ground-truth surface points."""
    last = model.trajectory_means.shape[1] - 1
    points_last = np.asarray(gt_observed["points3d"], np.float64)[:, -1]
    idx, w, off = attach_points(points_last, np.asarray(model.trajectory_means[:, last], np.float64),
                                np.asarray(model.trajectory_quats[:, last], np.float64), k)
    return carry_points(idx, w, off, np.asarray(fc["means"], np.float64), np.asarray(fc["quats"], np.float64))


def tracking_section(model: Model4D, fc: dict[str, Any], scene_h5: str, split: Split,
                     params: Mapping[str, Any]) -> tuple[dict[str, Any] | None, float | None]:
    """Tracking metrics of the GT surface points carried by the forecast, and
    the quick 3D check: their mean distance from the GT over every point and
    forecast step (no visibility, no unit scaling). (None, None) without GT."""
    from . import metrics as M
    from .camera import project

    gt_obs = load_ground_truth(scene_h5, split, "observed")
    if "points3d" not in gt_obs:
        return None, None
    gt_fc = load_ground_truth(scene_h5, split, "forecast")
    pred3d = predicted_gt_tracks(model, fc, gt_obs, int(params["tracking_neighbors"]))
    gt3d = np.asarray(gt_fc["points3d"], np.float64)
    epe_3d_quick = float(np.mean(np.linalg.norm(pred3d - gt3d, axis=-1)))
    P, T = gt3d.shape[:2]
    gt_vis = np.asarray(gt_fc.get("visible", np.ones((P, T), bool)), bool)
    pred2d = gt2d = pred_vis = None
    if "tracks2d" in gt_fc and split.frame_ids["train_future"].size:
        frames = load_frames(scene_h5, split, "train_future")
        by_t = {int(t): f for f, t in enumerate(frames.time_index)}
        pred2d = np.zeros((P, T, 2))
        pred_vis = np.zeros((P, T), bool)
        for i, t in enumerate(split.forecast_timesteps):
            f = by_t.get(int(t))
            if f is None:
                continue
            uv, z = project(pred3d[:, i], frames.K[f], frames.w2c[f])
            pred2d[:, i] = uv
            out = render_poses(model, fc["means"][:, i], fc["quats"][:, i], frames.K[f], frames.w2c[f], frames.width, frames.height)
            depth = out.depth[..., 0].detach().cpu().numpy()
            col = np.clip(np.floor(uv[:, 0]).astype(int), 0, frames.width - 1)
            row = np.clip(np.floor(uv[:, 1]).astype(int), 0, frames.height - 1)
            inside = (uv[:, 0] >= 0) & (uv[:, 0] < frames.width) & (uv[:, 1] >= 0) & (uv[:, 1] < frames.height) & (z > 0)
            surface = depth[row, col]
            pred_vis[:, i] = inside & (z <= surface * (1.0 + float(params["visibility_tolerance"])))
        gt2d = np.asarray(gt_fc["tracks2d"], np.float64)
    res = M.tracking_metrics(
        gt_vis=gt_vis, pred_vis=pred_vis, pred_3d=pred3d, gt_3d=gt3d, pred_2d=pred2d, gt_2d=gt2d,
        scale=float(params["tracking_scale"]), aj_thresholds=tuple(params["aj_thresholds"]),
        pck_thresholds=tuple(params["delta_thresholds"]), strict=False,
    )
    return {k: (None if v is None else float(v)) for k, v in res.items()}, epe_3d_quick


# ------------------------------------------------------------------ stage
def runtime_section(benchmarks: Mapping[str, str], methods: list[str]) -> dict[str, Any]:
    stages = {name: read_benchmark(path) for name, path in sorted(benchmarks.items())}
    shared = sum(v["wall_s"] for k, v in stages.items() if not k.startswith("forecast_"))
    per_method = {}
    for m in methods:
        own = sum(v["wall_s"] for k, v in stages.items() if k == f"forecast_{m}" or k.startswith(f"forecast_{m}_group"))
        per_method[m] = round(shared + own, 3)
    return {"stages": stages, "total_wall_s": per_method}


def run_evaluate_stage(*, scene: str, split: str, model: str, reconstruction_quality: str, grouping_quality: str, forecasts: Mapping[str, str],
                       benchmarks: Mapping[str, str], out_metrics: str, out_renders: str, params: Mapping[str, Any], variant: str,
                       ids: Mapping[str, str]) -> Path:
    """metrics.json and renders of every forecast. `model`: the model the
    forecasts start from (refined.h5, or recon.h5 without refinement);
    `reconstruction_quality`: reconstruction_quality/{refined,recon}.h5 of that model;
    `grouping_quality`: grouping_quality.h5 of the grouping the forecasts used."""
    refuse_unknown_params("evaluate", params, DEFAULT_PARAMS)
    p = {**DEFAULT_PARAMS, **dict(params)}
    start = time.perf_counter()
    if p["lpips"]:
        from .metrics.lpips import load_lpips_weights

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
    renders_tmp = Path(out_renders).with_name(f".{Path(out_renders).name}.tmp-{os.getpid()}")
    shutil.rmtree(renders_tmp, ignore_errors=True)
    renders_tmp.mkdir(parents=True)
    gts = [frames.images[f] / 255.0 for f in range(frames.num_frames)]
    result: dict[str, Any] = {
        "mogaf_version": __version__,
        "dataset": ids.get("dataset"), "scene": ids.get("scene"), "ratio": sp.ratio, "variant": variant,
        "protocol": sp.protocol, "num_evaluation_views": int(frames.num_frames),
        "forecast_timesteps": [int(t) for t in sp.forecast_timesteps],
        "methods": {},
    }
    labels: dict[str, str] = {}
    side_by_side: dict[str, list[np.ndarray]] = {}  # uint8 renders for all_methods.mp4
    try:
        for method in methods:
            fc = read_forecast(forecasts[method])
            _check_forecast(fc, m4, sp)
            renders = render_forecast_views(m4, fc, frames, p)
            per = [image_metrics(renders[f], gts[f], None if masks is None else masks[f], masked, bool(p["lpips"])) for f in range(frames.num_frames)]
            section: dict[str, Any] = {"image": mean_metrics(per),
                                       "per_view": [{"frame": frames.frame_names[f], "timestep": int(frames.time_index[f]), **per[f]} for f in range(frames.num_frames)]}
            section["tracking"], epe_3d_quick = tracking_section(m4, fc, scene, sp, p)
            section["forecast"] = forecast_summary(fc["attrs"])
            if epe_3d_quick is not None:
                section["forecast"]["epe_3d_quick"] = epe_3d_quick
            result["methods"][method] = section
            if p["save_renders"]:
                for f in range(frames.num_frames):
                    _save_png(renders_tmp / method / f"{frames.frame_names[f]}.png", renders[f])
            if p["video"]:
                label = method_label({"methods": {method: section}}, method)
                labels[method] = label
                panels = [labelled_row([gts[f], renders[f], np.abs(renders[f] - gts[f])], ["GT", label, "|error|"],
                                       f"{label}, time step {int(frames.time_index[f])}, view {frames.frame_names[f]}")
                          for f in range(frames.num_frames)]
                _write_video(renders_tmp / f"{method}.mp4", panels, int(p["video_fps"]))
                side_by_side[method] = [to_uint8(r) for r in renders]
        if p["video"] and len(methods) > 1:
            # one video of every method beside the GT, in the tables' order
            order = sorted(methods, key=lambda m: METHOD_ORDER.index(m) if m in METHOD_ORDER else len(METHOD_ORDER))
            panels = [labelled_row([gts[f]] + [side_by_side[m][f] for m in order], ["GT"] + [labels[m] for m in order],
                                   f"time step {int(frames.time_index[f])}, view {frames.frame_names[f]}")
                      for f in range(frames.num_frames)]
            _write_video(renders_tmp / "all_methods.mp4", panels, int(p["video_fps"]))
        result["reconstruction"] = reconstruction
        result["grouping"] = grouping
        if p["runtime_in_metrics"]:
            rt = runtime_section(benchmarks, methods)
            rt["stages"]["evaluate"] = {"wall_s": round(time.perf_counter() - start, 3), "max_rss_mb": None}
            result["runtime"] = rt
            for method in methods:
                result["methods"][method]["runtime"] = {"total_wall_s": rt["total_wall_s"][method]}
        final = Path(out_renders)
        if final.exists():
            shutil.rmtree(final)
        os.replace(renders_tmp, final)
    finally:
        shutil.rmtree(renders_tmp, ignore_errors=True)
    return write_json(out_metrics, _round(result))
