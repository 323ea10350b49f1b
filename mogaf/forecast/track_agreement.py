"""How far the reconstruction's last observed motion agrees with the 2D tracks.

A forecast extrapolates the reconstruction's motion at its last observed
steps. The 2D tracks of the priors stage (observed frames only) see that
motion in the image. Over the last `track_steps` observed steps, for every
track on a rigid body the forecast moves:

    predicted  = P_end(X_end) - P_start(X_start)   the body's points, projected
    observed   = xy_end - xy_start                 the track
    camera     = P_end(X_start) - P_start(X_start) the same point, held still

(X: the model's expected surface point under the track at each step, P: each
frame's camera). The body's own image motion is m = mean |observed - camera|,
its estimate's error e = mean |predicted - observed|. For a velocity v
estimated as v + err with |err| = (e / m) |v|, the err uncorrelated with v,
the scale s minimising E |s (v + err) - v|^2 is

    s = m^2 / (m^2 + e^2),

so the structured forecaster (`forecast.mogaf.structured.track_agreement:
shrink`) scales each body's forecast motion from its last observed pose by s:
its centroid path and its rotation angle, so it stays rigid. A body with
fewer than `min_tracks` tracks takes its job's figures over every track on
its members; a job with fewer keeps its forecast. Without tracks (multi-view
layouts, whose camera jumps between views) nothing changes.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from ..camera import project
from ..errors import input_error
from ..split import Split
from . import quat
from .trajectory import accumulated_rotvec, integrate_rotvec, rigid_decomposition


@dataclass(frozen=True)
class TrackWindow:
    """The tracks visible at two observed steps and those steps' cameras."""

    step_start: int
    step_end: int
    xy_start: np.ndarray  # (N, 2) pixels, pixel centres at i + 0.5
    xy_end: np.ndarray  # (N, 2)
    K_start: np.ndarray  # (3, 3)
    w2c_start: np.ndarray  # (4, 4)
    K_end: np.ndarray
    w2c_end: np.ndarray
    width: int
    height: int


def observed_track_window(
    priors_h5: str | os.PathLike, scene_h5: str | os.PathLike, split: Split, steps: int
) -> TrackWindow | None:
    """The priors' tracks at the last observed step and `steps` steps before,
    with those two frames' cameras (scene.h5). None without tracks, or with
    too few observed steps. Only those two frames are read: nothing of a
    forecast step."""
    from ..artefact import open_artefact
    from ..artefact.reader import read_rows
    from ..grouping.stage import PRIORS_STAGE
    from ..scene import SCENE_STAGE, check_scene_file

    observed = np.sort(np.asarray(split.observed_timesteps, np.int64))
    if observed.size <= steps:
        return None
    step_start, step_end = int(observed[-1 - steps]), int(observed[-1])
    with open_artefact(priors_h5, PRIORS_STAGE) as fh:
        if "tracks/xy" not in fh or fh["tracks/xy"].shape[0] == 0:
            return None
        frame_ids = np.asarray(fh["frame_ids"][()], np.int64)
        timesteps = np.asarray(fh["timesteps"][()], np.int64)
        if not np.array_equal(np.sort(frame_ids), np.sort(np.asarray(split.frame_ids["observed"], np.int64))):
            raise input_error(priors_h5, "its frames are not the split's observed frames: made for another split")
        missing = [step for step in (step_start, step_end) if step not in timesteps]
        if missing:
            raise input_error(priors_h5, f"has no frame at observed time step {missing[0]}: made for another scene")
        rows = [int(np.flatnonzero(timesteps == step)[0]) for step in (step_start, step_end)]
        order = np.argsort(rows)  # h5py reads columns in increasing order only
        picked = np.asarray(rows)[order]
        back = np.argsort(order)
        xy = np.asarray(fh["tracks/xy"][:, picked], np.float64)[:, back]
        visible = np.asarray(fh["tracks/visible"][:, picked], bool)[:, back]
    ids = frame_ids[rows]
    with open_artefact(scene_h5, SCENE_STAGE) as fh:
        check_scene_file(fh, scene_h5)
        if not np.array_equal(read_rows(fh, "frames/time_index", ids), [step_start, step_end]):
            raise input_error(priors_h5, f"its frames' time steps are not those of {scene_h5}: made for another scene")
        K = np.asarray(read_rows(fh, "frames/K", ids), np.float64)
        w2c = np.asarray(read_rows(fh, "frames/w2c", ids), np.float64)
        width, height = int(fh.attrs["width"]), int(fh.attrs["height"])
    both = visible.all(axis=1) & np.isfinite(xy).all(axis=(1, 2))
    return TrackWindow(step_start, step_end, xy[both, 0], xy[both, 1], K[0], w2c[0], K[1], w2c[1], width, height)


def sample_bilinear(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(N, C) values of an (H, W, C) image at continuous pixel positions (N, 2)
    (pixel i's centre at i + 0.5; clamped at the borders)."""
    h, w = image.shape[:2]
    x = np.clip(np.asarray(xy[:, 0], np.float64) - 0.5, 0.0, w - 1.0)
    y = np.clip(np.asarray(xy[:, 1], np.float64) - 0.5, 0.0, h - 1.0)
    x0, y0 = (
        np.minimum(np.floor(x).astype(np.int64), w - 2 if w > 1 else 0),
        np.minimum(np.floor(y).astype(np.int64), h - 2 if h > 1 else 0),
    )
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def _project(points: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> np.ndarray:
    return project(points, K, w2c)[0]


def track_motion_errors(
    model, members: np.ndarray, bodies: np.ndarray, window: TrackWindow, backend: str = "auto"
) -> dict[int, tuple[float, float, int]]:
    """body -> (e, m, n): the mean image-plane error (pixels) of the model's
    motion over the window against the tracks on the body, the tracks' own
    motion with the camera's taken out, and the number of tracks; key -1
    pools every track on the job's members. A track belongs to the body
    covering more than half of its pixel at the window's end (the model
    rendered there with every Gaussian, so occluders count)."""
    from ..rendering import render_model, timestep_position

    steps = np.asarray(model.timesteps)
    k_start, k_end = timestep_position(model, window.step_start), timestep_position(model, window.step_end)
    labels = np.asarray(bodies, np.int64)
    names = np.unique(labels)
    n_fg = len(model.fg)
    n_bg = 0 if model.bg is None else len(model.bg)
    feats = np.zeros((n_fg + n_bg, 6 + names.size), np.float32)
    feats[members, 0:3] = model.trajectory_means[members, k_end]
    feats[members, 3:6] = model.trajectory_means[members, k_start]
    feats[members, 6 + np.searchsorted(names, labels)] = 1.0
    out = render_model(
        model,
        int(steps[k_end]),
        window.K_end,
        window.w2c_end,
        window.width,
        window.height,
        features=feats,
        backend=backend,
    )
    image = np.asarray(out.features, np.float64)
    inside = (
        (window.xy_end[:, 0] >= 0)
        & (window.xy_end[:, 1] >= 0)
        & (window.xy_end[:, 0] < window.width)
        & (window.xy_end[:, 1] < window.height)
    )
    values = sample_bilinear(image, window.xy_end[inside])
    shares = values[:, 6:]
    job_share = shares.sum(axis=1)
    on_job = job_share > 0.5
    values, shares, job_share = values[on_job], shares[on_job], job_share[on_job]
    xy_start, xy_end = window.xy_start[inside][on_job], window.xy_end[inside][on_job]
    x_end = values[:, 0:3] / job_share[:, None]
    x_start = values[:, 3:6] / job_share[:, None]
    predicted = _project(x_end, window.K_end, window.w2c_end) - _project(x_start, window.K_start, window.w2c_start)
    camera = _project(x_start, window.K_end, window.w2c_end) - _project(x_start, window.K_start, window.w2c_start)
    observed = xy_end - xy_start
    error = np.linalg.norm(predicted - observed, axis=1)
    motion = np.linalg.norm(observed - camera, axis=1)
    owner = names[np.argmax(shares, axis=1)] if shares.size else np.zeros(0, np.int64)
    figures = {-1: (_mean(error), _mean(motion), int(error.size))}
    for body in names[names >= 0]:
        pick = (owner == body) & (shares.max(axis=1, initial=0.0) > 0.5)
        figures[int(body)] = (_mean(error[pick]), _mean(motion[pick]), int(pick.sum()))
    return figures


def _mean(x: np.ndarray) -> float:
    return float(x.mean()) if x.size else 0.0


# A member turned by less (radians) is still: its quaternion's renormalisation.
TURN_TOLERANCE = 1e-9


def agreement_scale(error: float, motion: float) -> float:
    """m^2 / (m^2 + e^2): the scale of an estimated motion whose error is e
    against the motion's own size m (1 where the error is none)."""
    if error <= 0.0:
        return 1.0
    return float(motion * motion / (motion * motion + error * error))


def body_scales(figures: dict[int, tuple[float, float, int]], min_tracks: int) -> dict[int, float]:
    """body -> scale: its own figures' with at least min_tracks tracks, else
    the job's (key -1) with as many, else 1."""
    e, m, n = figures[-1]
    pooled = agreement_scale(e, m) if n >= min_tracks else 1.0
    out = {-1: pooled}
    for body, (e, m, n) in figures.items():
        if body >= 0:
            out[body] = agreement_scale(e, m) if n >= min_tracks else pooled
    return out


def scale_motion(
    last: np.ndarray, poses: np.ndarray, bodies: np.ndarray | None, scales: dict[int, float]
) -> np.ndarray:
    """Forecast poses (G, T, 7) [mu, q wxyz] with each member's motion from
    its last observed pose (G, 7) scaled by its body's scale (bodies (G,),
    Forecaster.bodies(); -1 or None: the member on its own, scale scales[-1]).
    A rigid body's centroid path and rotation (its best rigid fit) are scaled,
    so it stays rigid; a member moved on its own has its displacement and its
    accumulated rotation scaled. Members the forecast keeps still stay still;
    a scale of 1 leaves a member's poses as they are."""
    last = np.asarray(last, np.float64)
    out = np.array(poses, np.float64)
    labels = np.full(last.shape[0], -1, np.int64) if bodies is None else np.asarray(bodies, np.int64)
    # positions compared bit for bit; orientations by angle (the forecaster renormalises them)
    moving = np.any(out[..., :3] != last[:, None, :3], axis=(1, 2)) | np.any(
        quat.angle_between(last[:, None, 3:], out[..., 3:]) > TURN_TOLERANCE, axis=1
    )
    on_own = (labels < 0) & moving
    for body in np.unique(labels[labels >= 0]):
        members = np.flatnonzero((labels == body) & moving)
        s = float(scales.get(int(body), scales[-1]))
        if members.size < 3:  # too few for a rigid fit: each member on its own, at the body's scale
            if s != 1.0 and members.size:
                out[members] = _scaled_each(last[members], out[members], s)
        elif s != 1.0:
            out[members] = _scaled_rigid(last[members], out[members], s)
    if on_own.any() and scales[-1] != 1.0:
        out[on_own] = _scaled_each(last[on_own], out[on_own], float(scales[-1]))
    return out


def _scaled_rigid(last: np.ndarray, poses: np.ndarray, s: float) -> np.ndarray:
    positions = np.concatenate([poses[..., :3], last[:, None, :3]], axis=1)
    centroids, rotations, _ = rigid_decomposition(positions)
    sequence = np.concatenate([rotations[-1:], rotations[:-1]], axis=0)  # the last observed pose first
    turned = integrate_rotvec(sequence[0], np.zeros(3), s * accumulated_rotvec(sequence)[1:])
    centre = centroids[-1]
    path = centre + s * (centroids[:-1] - centre)
    out = np.empty_like(poses)
    out[..., :3] = path[None] + quat.rotate(turned[None], (last[:, :3] - centre)[:, None])
    out[..., 3:] = quat.align_to(quat.mul(turned[None], last[:, None, 3:]), poses[..., 3:])
    return out


def _scaled_each(last: np.ndarray, poses: np.ndarray, s: float) -> np.ndarray:
    out = np.empty_like(poses)
    out[..., :3] = last[:, None, :3] + s * (poses[..., :3] - last[:, None, :3])
    sequence = np.concatenate([last[:, None, 3:], poses[..., 3:]], axis=1)
    turned = integrate_rotvec(last[:, 3:], np.zeros((last.shape[0], 3)), s * accumulated_rotvec(sequence)[:, 1:])
    out[..., 3:] = quat.align_to(turned, poses[..., 3:])
    return out
