"""Which directions of motion the observed views constrain.

A reconstruction from one slowly moving camera (a phone video) sees an
object's motion across the camera's rays, and along them only through depth
cues, so the velocity it ends with is least accurate, and often wrong by more
than its size, along the rays. The structured MoGaF forecaster
(`forecast.mogaf.structured.unobserved_motion`) scales each forecast
displacement down along such directions:

    M = mean over views of (I - d d^T),  d the unit ray from a view's camera
        centre to the group's centre at the last observed step;

u^T M u is the mean squared sine of the angle between a unit direction u and
the rays: 1 for a direction every view sees across, 0 along every ray. Along
each eigenvector of M the displacement is scaled by min(1, lambda /
sin^2(min_spread)): a direction the rays meet at `min_spread` or more (in
mean squared sine) keeps its forecast motion; views spread around the scene
(as the MuJoCo grid's renders) leave every direction as it is. Each rigid
body the forecast moves is scaled as one (suppress_unobserved).
"""

from __future__ import annotations

import os

import numpy as np

from ..split import Split


def observed_view_centres(scene_h5: str | os.PathLike, split: Split, steps: int) -> np.ndarray:
    """Camera centres (V, 3) of the observed frames at the last `steps` observed
    time steps. Only those frames' poses and time steps are read: no image,
    nothing of a forecast step."""
    from ..artefact import open_artefact
    from ..artefact.reader import read_rows
    from ..camera import camera_centers
    from ..scene import SCENE_STAGE, check_scene_file
    from ..split.frames import check_role_steps

    ids = np.asarray(split.frame_ids["observed"], np.int64)
    with open_artefact(scene_h5, SCENE_STAGE) as fh:
        check_scene_file(fh, scene_h5)
        time_index = read_rows(fh, "frames/time_index", ids)
        check_role_steps(scene_h5, split, "observed", time_index)
        recent = np.sort(np.unique(time_index))[-int(steps) :]
        w2c = read_rows(fh, "frames/w2c", ids[np.isin(time_index, recent)])
    return camera_centers(np.asarray(w2c, np.float64))


def view_information(points: np.ndarray, camera_centres: np.ndarray) -> np.ndarray:
    """(..., 3, 3) for points (..., 3): the mean over the views of I - d d^T,
    d the unit ray from each camera centre (V, 3) to the point; a view at the
    point itself is left out, and a point no view sees gets zeros."""
    rays = np.asarray(points, np.float64)[..., None, :] - np.asarray(camera_centres, np.float64)
    length = np.linalg.norm(rays, axis=-1, keepdims=True)
    valid = length[..., 0] > 1e-12
    unit = np.where(valid[..., None], rays / np.where(length > 1e-12, length, 1.0), 0.0)
    count = valid.sum(axis=-1)[..., None, None]
    mean_outer = np.einsum("...vi,...vj->...ij", unit, unit) / np.maximum(count, 1)
    return np.where(count > 0, np.eye(3) - mean_outer, 0.0)


def unobserved_scaling(information: np.ndarray, min_spread_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For information (..., 3, 3): the symmetric maps (..., 3, 3) scaling a
    displacement by min(1, lambda / sin^2(min_spread)) along each eigenvector,
    whether each scales anything (...,), and its smallest scale (...,). Where
    every direction is seen at `min_spread` or more, or no view sees the point
    (nothing known), the map is the identity and scales nothing."""
    info = np.asarray(information, np.float64)
    lam, vectors = np.linalg.eigh(info)
    scale = np.minimum(1.0, np.clip(lam, 0.0, None) / np.sin(np.radians(float(min_spread_deg))) ** 2)
    scaled = (np.trace(info, axis1=-2, axis2=-1) > 0) & np.any(scale < 1.0, axis=-1)
    scale = np.where(scaled[..., None], scale, 1.0)
    maps = np.einsum("...ik,...k,...jk->...ij", vectors, scale, vectors)
    return np.where(scaled[..., None, None], maps, np.eye(3)), scaled, scale.min(axis=-1)


def suppress_unobserved(
    last_means: np.ndarray,
    means: np.ndarray,
    bodies: np.ndarray | None,
    camera_centres: np.ndarray,
    min_spread_deg: float,
) -> tuple[np.ndarray, dict[str, float]]:
    """Forecast positions (G, T, 3) with each displacement from the last
    observed position (G, 3) scaled down along the directions the views
    (camera centres (V, 3)) did not see across, and the figures: the least
    mean squared sine of a direction with the rays (`view_spread_min`) and the
    smallest scale applied (`unobserved_scale_min`).

    `bodies` (G,): Forecaster.bodies(). A rigid body's moving members share
    the correction of their mean displacement, scaled at their centroid, so
    the body stays rigid (its turn is seen across the rays); a member moved
    on its own (-1, or bodies None) is scaled at its own position. Members the
    forecast keeps still stay still; where nothing is scaled, the positions
    are returned as they are."""
    last = np.asarray(last_means, np.float64)
    out = np.array(means, np.float64)
    displacement = out - last[:, None]
    moving = np.any(displacement != 0.0, axis=(1, 2))
    labels = np.full(last.shape[0], -1, np.int64) if bodies is None else np.asarray(bodies, np.int64)
    spreads, scales = [], []
    for body in np.unique(labels[labels >= 0]):
        members = np.flatnonzero((labels == body) & moving)
        if members.size == 0:
            continue
        information = view_information(last[members].mean(axis=0), camera_centres)
        scaling, scaled, smallest = unobserved_scaling(information, min_spread_deg)
        spreads.append(np.linalg.eigvalsh(information)[0])
        scales.append(smallest)
        if scaled:
            out[members] -= (displacement[members].mean(axis=0) @ (np.eye(3) - scaling).T)[None]
    own = np.flatnonzero((labels < 0) & moving)
    if own.size:
        information = view_information(last[own], camera_centres)
        scaling, scaled, smallest = unobserved_scaling(information, min_spread_deg)
        spreads.append(np.linalg.eigvalsh(information)[:, 0].min())
        scales.append(smallest.min())
        pick = own[scaled]
        out[pick] = last[pick, None] + np.einsum("gij,gtj->gti", scaling[scaled], displacement[pick])
    figures = {"view_spread_min": float(min(spreads)), "unobserved_scale_min": float(min(scales))} if spreads else {}
    return out, figures
