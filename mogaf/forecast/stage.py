"""Forecast stage: one job per dynamic motion group and method, then a merge
(forecast.jobs: per_method: every group of a method inside its merge job).

forecast/{method}/group{k}.h5 (stage "forecast_group"): the poses of group k's
Gaussians at every forecast time step, predicted from the group's observed
trajectories only. k = "all" when group-wise forecasting is off (ablation
"w/o group-wise forecasting": one forecaster for every dynamic Gaussian).
forecast/{method}.h5 (stage "forecast"): poses of every dynamic Gaussian at
every forecast time step; Gaussians of static groups keep their last
observed pose (no forecaster is trained for them).

Schema of forecast/{method}.h5:
  timesteps (T_fc,)        scene time-grid indices (= split.forecast_timesteps)
  means (N, T_fc, 3), quats (N, T_fc, 4)   per fg Gaussian, wxyz, unit
  group_id (N,)
attrs: method, groupwise, job_layout (forecast.jobs), num_groups_trained, flags (per job), params.

A forecast job uses of the scene only the observed frames' camera poses (the
structured MoGaF's unobserved_motion: mogaf.forecast.observability), and of
the priors the 2D tracks at two observed steps (its track_agreement:
mogaf.forecast.track_agreement):
the future (ground truth included) is read only by the evaluation stage, which
also computes the quick 3D check.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..artefact import config_digest, read_artefact, write_artefact
from ..devices import torch_threads
from ..errors import MogafError, input_error
from ..representation import Model4D, load_model, quat_sign_continuity
from ..split import read_split
from .coherence import coherence
from .observability import observed_view_centres, suppress_unobserved
from .params import INLINE_METHODS, JOB_LAYOUTS, param_section, section_params
from .registry import fit_and_rollout, load_settings
from .track_agreement import TrackWindow, body_scales, observed_track_window, scale_motion, track_motion_errors

log = logging.getLogger(__name__)

GROUP_STAGE = "forecast_group"
MERGE_STAGE = "forecast"
ALL = "all"


def _groups(groups_h5: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    art = read_artefact(groups_h5, "group", required=["group_id", "group_static"])
    return np.asarray(art["group_id"], np.int64), np.asarray(art["group_static"], bool)


def group_rigid_flags(groups_h5: str | os.PathLike) -> np.ndarray:
    """(K,) the grouping's rigid flag of every group."""
    art = read_artefact(groups_h5, "group", required=["group_rigid", "group_static"])
    flags = np.asarray(art["group_rigid"], bool)
    if flags.shape != np.asarray(art["group_static"]).shape:
        raise input_error(
            groups_h5, f"group_rigid has {flags.size} groups, group_static {np.asarray(art['group_static']).size}"
        )
    return flags


def job_rigid_hint(job: str, group_rigid: np.ndarray) -> bool | None:
    """The grouping's rigid flag for a group job; None for the job of every
    dynamic Gaussian (its members are no one rigid body)."""
    return None if job == ALL else bool(group_rigid[int(job)])


def dynamic_members(group_id: np.ndarray, group_static: np.ndarray) -> np.ndarray:
    """Indices of Gaussians in non-static groups."""
    dynamic = np.flatnonzero(~group_static)
    return np.flatnonzero(np.isin(group_id, dynamic))


# Methods with nothing to train (params.INLINE_METHODS) run inside the merge
# job: a Snakemake job of their own would take longer to start than to run.
# forecast.jobs: per_method runs every method so: one process (torch's import,
# the inputs) per method instead of one per group, the same forecasts.


def job_layout(params: Mapping[str, Any]) -> str:
    """forecast.jobs of a forecast section (per_group when absent)."""
    return _checked_layout(params.get("jobs", "per_group"))


def _checked_layout(layout: str) -> str:
    if layout not in JOB_LAYOUTS:
        raise MogafError(f"forecast.jobs must be one of {', '.join(JOB_LAYOUTS)}, got {layout!r}")
    return layout


def merge_computes(method: str, layout: str) -> bool:
    """Whether `method`'s merge job computes its groups itself: INLINE_METHODS
    always, every method under layout per_method."""
    return method in INLINE_METHODS or _checked_layout(layout) == "per_method"


def method_jobs(method: str, jobs: list[str], layout: str = "per_group") -> list[str]:
    """Of the forecast jobs (forecast_jobs), those `method` runs as separate
    forecast_group jobs: all of them, or none where its merge job computes them."""
    return [] if merge_computes(method, layout) else list(jobs)


def _job_names(group_id: np.ndarray, group_static: np.ndarray, groupwise: bool) -> list[str]:
    dynamic = [k for k in np.flatnonzero(~group_static) if np.any(group_id == k)]
    if not dynamic:
        return []
    return [str(int(k)) for k in dynamic] if groupwise else [ALL]


def forecast_jobs(groups_h5: str | os.PathLike, *, groupwise: bool) -> list[str]:
    """Job names: dynamic group ids (as text), or ['all']; [] for a static scene."""
    group_id, group_static = _groups(groups_h5)
    return _job_names(group_id, group_static, groupwise)


def job_members(job: str, group_id: np.ndarray, group_static: np.ndarray, source: str | os.PathLike) -> np.ndarray:
    if job == ALL:
        members = dynamic_members(group_id, group_static)
    else:
        try:
            k = int(job)
        except ValueError:
            raise MogafError(f"forecast job '{job}' is neither a group id nor '{ALL}'") from None
        if k < 0 or k >= group_static.size:
            raise input_error(source, f"has {group_static.size} groups, no group {k}")
        if group_static[k]:
            raise input_error(source, f"group {k} is static: it is not forecast (its future is its last pose)")
        members = np.flatnonzero(group_id == k)
    if members.size == 0:
        raise input_error(source, f"forecast job '{job}' has no Gaussians")
    return members


def observed_states(model: Model4D, members: np.ndarray) -> np.ndarray:
    """(G, T, 7) float64 [mu, q] with quaternion sign continuity along time."""
    means = np.asarray(model.trajectory_means[members], np.float64)
    quats = quat_sign_continuity(np.asarray(model.trajectory_quats[members], np.float64), axis=1)
    return np.concatenate([means, quats], axis=-1)


def method_params(params: Mapping[str, Any], method: str) -> dict[str, Any]:
    return {**dict(params.get("common") or {}), **section_params(method, params.get(param_section(method)))}


def _job_seed(seed: int, job: str) -> int:
    # Distinct, reproducible streams per job; "all" uses the base seed.
    return int(seed) if job == ALL else int(seed) + 1000 * (int(job) + 1)


def _load_inputs(model_h5, groups_h5, split_h5):
    """The model, its groups and the split. That groups_h5 groups this very
    model's Gaussians is the stage's check (mogaf.stages.forecast_group and
    forecast_merge), made before this runs."""
    model = load_model(model_h5)
    group_id, group_static = _groups(groups_h5)
    split = read_split(split_h5)
    if model.trajectory_means.shape[1] != split.num_observed_timesteps:
        raise input_error(
            model_h5,
            f"trajectories have {model.trajectory_means.shape[1]} steps, "
            f"the split observes {split.num_observed_timesteps}",
        )
    return model, group_id, group_static, split


def _structured_switched_on(settings: Any, switch: str, on: str) -> Any:
    """The structured settings of a MoGaF run whose `switch` is `on`
    (unobserved_motion: suppress, track_agreement: shrink), else None."""
    own, net = getattr(settings, "own", None), getattr(settings, "net", None)
    if own is None or net is None or net.mode != "structured" or getattr(own, switch) != on:
        return None
    return own


def job_view_centres(settings: Any, scene_h5: str | os.PathLike | None, split: Any, method: str) -> np.ndarray | None:
    """The camera centres a method's jobs weigh their forecast motion by
    (structured MoGaF, unobserved_motion: suppress), else None."""
    own = _structured_switched_on(settings, "unobserved_motion", "suppress")
    if own is None:
        return None
    if scene_h5 is None:
        raise MogafError(
            f"forecast {method}: forecast.mogaf.structured.unobserved_motion: suppress reads the observed frames' "
            "camera poses: give the scene (--scene-h5), or set unobserved_motion: keep"
        )
    return observed_view_centres(scene_h5, split, own.view_window)


def job_track_window(
    settings: Any,
    priors_h5: str | os.PathLike | None,
    scene_h5: str | os.PathLike | None,
    split: Any,
    method: str,
) -> TrackWindow | None:
    """The tracks a method's jobs compare their bodies' last observed motion
    with (structured MoGaF, track_agreement: shrink), else None (also when the
    priors have no tracks)."""
    own = _structured_switched_on(settings, "track_agreement", "shrink")
    if own is None:
        return None
    if priors_h5 is None or scene_h5 is None:
        raise MogafError(
            f"forecast {method}: forecast.mogaf.structured.track_agreement: shrink reads the priors' 2D tracks and "
            "the observed frames' cameras: give the priors (--priors-h5) and the scene (--scene-h5), or set "
            "track_agreement: keep"
        )
    return observed_track_window(priors_h5, scene_h5, split, own.track_steps)


def forecast_job(
    model: Model4D,
    members: np.ndarray,
    horizon: int,
    settings: Any,
    method: str,
    job: str,
    seed: int,
    rigid: bool | None = None,
    device: str = "cpu",
    view_centres: np.ndarray | None = None,
    track_window: TrackWindow | None = None,
) -> tuple[np.ndarray, dict[str, Any], float]:
    """Fit `method` on the members' observed trajectories; (poses (G, horizon, 7), info, wall seconds).
    `settings`: the method's, loaded once for the job (registry.load_settings);
    `rigid`: the grouping's rigid flag of the job's group (None for the job of every dynamic Gaussian);
    `device`: auto | cpu | cuda, where a torch-based method computes;
    `view_centres`: job_view_centres' (None: the forecast as fitted);
    `track_window`: job_track_window's (None: the forecast as fitted). The
    forecaster refuses non-finite poses (Forecaster.rollout)."""
    observed = observed_states(model, members)
    start = time.perf_counter()
    result = fit_and_rollout(method, observed, horizon, settings, _job_seed(seed, job), rigid=rigid, device=device)
    wall = time.perf_counter() - start
    poses = np.asarray(result.poses, np.float64)
    info = {k: v for k, v in dict(result.info).items() if isinstance(v, (int, float, str, bool)) or v is None}
    if view_centres is not None:
        poses = _suppress_unobserved_motion(poses, observed[:, -1, :3], view_centres, settings, info, result.bodies)
    if track_window is not None:
        poses = _scale_by_track_agreement(
            model, members, poses, observed[:, -1], track_window, settings, info, result.bodies
        )
    log.info("forecast %s job %s: %d Gaussians, %.1f s, info %s", method, job, members.size, wall, info)
    return poses, info, wall


def _suppress_unobserved_motion(
    poses: np.ndarray,
    last_means: np.ndarray,
    view_centres: np.ndarray,
    settings: Any,
    info: dict[str, Any],
    bodies: np.ndarray | None,
) -> np.ndarray:
    """poses with their displacement scaled down along the directions the views
    did not see across, body by body (mogaf.forecast.observability); info
    records the views' least mean squared sine and the smallest scale."""
    means, figures = suppress_unobserved(
        last_means,
        poses[..., :3],
        bodies,
        view_centres,
        _structured_switched_on(settings, "unobserved_motion", "suppress").observed_spread_deg,
    )
    info.update(figures)
    out = poses.copy()
    out[..., :3] = means
    return out


def _scale_by_track_agreement(
    model: Model4D,
    members: np.ndarray,
    poses: np.ndarray,
    last: np.ndarray,
    window: TrackWindow,
    settings: Any,
    info: dict[str, Any],
    bodies: np.ndarray | None,
) -> np.ndarray:
    """poses with each body's motion scaled by its agreement with the 2D
    tracks (mogaf.forecast.track_agreement); info records the job's tracks,
    their error and motion (pixels) and the smallest scale of its bodies."""
    labels = np.full(members.size, -1, np.int64) if bodies is None else np.asarray(bodies, np.int64)
    figures = track_motion_errors(model, members, labels, window)
    scales = body_scales(figures, int(_structured_switched_on(settings, "track_agreement", "shrink").min_tracks))
    error, motion, count = figures[-1]
    info.update(
        track_count=count,
        track_error_px=round(error, 4),
        track_motion_px=round(motion, 4),
        track_scale_min=round(min(scales.get(int(b), scales[-1]) for b in np.unique(labels)), 4),
    )
    return scale_motion(last, poses, labels, scales)


def run_forecast_group(
    model_h5: str,
    groups_h5: str,
    split_h5: str,
    out: str,
    params: Mapping[str, Any],
    *,
    method: str,
    job: str,
    seed: int,
    device: str = "cpu",
    scene_h5: str | None = None,
    priors_h5: str | None = None,
) -> Path:
    """One forecast_group job. Its settings are loaded and checked here, once
    (values without effect are said when the workflow starts: mogaf.config.inert_forecaster_settings).
    `scene_h5`: where the observed frames' camera poses are read (job_view_centres);
    `priors_h5`: where the 2D tracks are (job_track_window)."""
    settings = load_settings(method, method_params(params, method))
    model, group_id, group_static, split = _load_inputs(model_h5, groups_h5, split_h5)
    members = job_members(job, group_id, group_static, groups_h5)
    view_centres = job_view_centres(settings, scene_h5, split, method)
    track_window = job_track_window(settings, priors_h5, scene_h5, split, method)
    poses, info, wall = forecast_job(
        model,
        members,
        int(split.forecast_timesteps.size),
        settings,
        method,
        job,
        seed,
        job_rigid_hint(job, group_rigid_flags(groups_h5)),
        device,
        view_centres,
        track_window,
    )
    return write_artefact(
        out,
        GROUP_STAGE,
        {"members": members, "means": poses[..., :3].astype(np.float32), "quats": poses[..., 3:].astype(np.float32)},
        config_digest=config_digest(
            {
                "method": method,
                "params": method_params(params, method),
                "job": job,
                "seed": seed,
                # the device it ran on ("auto" resolved): CPU and GPU round differently
                "device": info.get("device"),
            }
        ),
        attrs={
            "method": method,
            "job": job,
            "num_gaussians": int(members.size),
            "fit_wall_s": round(wall, 3),
            "info": info,
        },
    )


def run_forecast_merge(
    model_h5: str,
    groups_h5: str,
    split_h5: str,
    parts: list[str],
    out: str,
    params: Mapping[str, Any],
    *,
    method: str,
    seed: int = 0,
    device: str | None = None,
    threads: int | None = None,
    scene_h5: str | None = None,
    priors_h5: str | None = None,
) -> Path:
    """Merge the group jobs' poses into forecast/{method}.h5. INLINE_METHODS,
    and every method under forecast.jobs: per_method, are computed here, group
    by group (a trained method on `device`, else params' `device`, else the
    CPU, with `threads` torch threads as a forecast_group job would be)."""
    layout = job_layout(params)
    if device is None:
        device = str(params.get("device", "cpu"))
    model, group_id, group_static, split = _load_inputs(model_h5, groups_h5, split_h5)
    group_rigid = group_rigid_flags(groups_h5)
    n, T = len(model.fg), int(split.forecast_timesteps.size)
    # Static groups (and anything no job covers) keep the last observed pose.
    means = np.repeat(np.asarray(model.trajectory_means[:, -1:], np.float32), T, axis=1)
    quats = np.repeat(np.asarray(model.trajectory_quats[:, -1:], np.float32), T, axis=1)
    covered = np.zeros(n, bool)
    flags = {}
    for part in parts:
        art = read_artefact(part, GROUP_STAGE, required=["members", "means", "quats"])
        if art.attrs.get("method") != method:
            raise input_error(part, f"holds method '{art.attrs.get('method')}', expected '{method}'")
        members = np.asarray(art["members"], np.int64)
        for key, width in (("means", 3), ("quats", 4)):
            if art[key].shape != (members.size, T, width):
                raise input_error(part, f"{key} have shape {art[key].shape}, expected ({members.size}, {T}, {width})")
        if np.any(covered[members]):
            raise input_error(part, "overlaps another forecast job")
        covered[members] = True
        means[members] = art["means"]
        quats[members] = art["quats"]
        flags[str(art.attrs.get("job"))] = art.attrs.get("info", {})
    trained = len(parts)
    if merge_computes(method, layout):
        if parts:
            raise MogafError(f"forecast {method}: computed in the merge job ({layout}), it takes no group files")
        settings = load_settings(method, method_params(params, method))  # once for every job of the merge
        view_centres = job_view_centres(settings, scene_h5, split, method)
        track_window = job_track_window(settings, priors_h5, scene_h5, split, method)
        jobs = _job_names(group_id, group_static, bool(params.get("groupwise", True)))
        untrained = method in INLINE_METHODS
        trained = 0 if untrained else len(jobs)
        with contextlib.nullcontext() if untrained else torch_threads(threads):
            for job in jobs:
                members = job_members(job, group_id, group_static, groups_h5)
                poses, info, _ = forecast_job(
                    model,
                    members,
                    T,
                    settings,
                    method,
                    job,
                    seed,
                    job_rigid_hint(job, group_rigid),
                    "cpu" if untrained else device,
                    view_centres,
                    track_window,
                )
                means[members] = poses[..., :3]
                quats[members] = poses[..., 3:]
                covered[members] = True
                flags[job] = info
    missing = dynamic_members(group_id, group_static)
    missing = missing[~covered[missing]]
    if missing.size:
        raise MogafError(f"forecast {method}: {missing.size} dynamic Gaussians are covered by no forecast job")
    mparams = method_params(params, method)
    structure = coherence(model.trajectory_means, means, group_id, group_static, group_rigid)
    attrs: dict[str, Any] = {
        "method": method,
        "groupwise": bool(params.get("groupwise", True)),
        "job_layout": layout,
        "num_groups_trained": trained,
        "flags": flags,
        "params": mparams,
        "coherence": structure,
    }
    return write_artefact(
        out,
        MERGE_STAGE,
        {"timesteps": split.forecast_timesteps, "means": means, "quats": quats, "group_id": group_id},
        config_digest=config_digest(
            {
                "method": method,
                "params": mparams,
                "seed": int(seed),
                "parts": sorted(Path(p).name for p in parts),
                # trained here: the devices it ran on ("auto" resolved), as a forecast_group job's digest has them
                **(
                    {"job_layout": layout, "devices": sorted({str(f.get("device")) for f in flags.values()})}
                    if trained and not parts
                    else {}
                ),
            }
        ),
        attrs=attrs,
    )
