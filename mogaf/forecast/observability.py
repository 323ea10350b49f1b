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
(D-NeRF-style renders) leave every direction as it is.
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import input_error
from ..split import Split


def observed_view_centres(scene_h5: str | os.PathLike, split: Split, steps: int) -> np.ndarray:
    """Camera centres (V, 3) of the observed frames at the last `steps` observed
    time steps. Only those frames' poses and time steps are read: no image,
    nothing of a forecast step."""
    from ..artefact import open_artefact
    from ..artefact.reader import read_rows
    from ..camera import camera_centers
    from ..scene import SCENE_STAGE, check_scene_file

    ids = np.asarray(split.frame_ids["observed"], np.int64)
    with open_artefact(scene_h5, SCENE_STAGE) as fh:
        check_scene_file(fh, scene_h5)
        time_index = read_rows(fh, "frames/time_index", ids)
        outside = ~np.isin(time_index, split.observed_timesteps)
        if outside.any():
            raise input_error(
                scene_h5,
                f"observed frame {int(ids[np.flatnonzero(outside)[0]])} is at a time step the split does not observe: "
                "the split was made for another scene",
            )
        recent = np.sort(np.unique(time_index))[-int(steps) :]
        w2c = read_rows(fh, "frames/w2c", ids[np.isin(time_index, recent)])
    return camera_centers(np.asarray(w2c, np.float64))


def view_information(point: np.ndarray, camera_centres: np.ndarray) -> np.ndarray:
    """(3, 3) mean over the views of I - d d^T, d the unit ray from each camera
    centre (V, 3) to `point` (3,); a view at the point itself is left out."""
    rays = np.asarray(point, np.float64)[None] - np.asarray(camera_centres, np.float64)
    length = np.linalg.norm(rays, axis=1)
    rays = rays[length > 1e-12] / length[length > 1e-12, None]
    if rays.shape[0] == 0:
        return np.zeros((3, 3))
    return np.eye(3) - np.einsum("vi,vj->ij", rays, rays) / rays.shape[0]


def unobserved_scaling(information: np.ndarray, min_spread_deg: float) -> np.ndarray | None:
    """(3, 3) symmetric map scaling a displacement by min(1, lambda / sin^2(min_spread))
    along each eigenvector of `information`; None where it scales nothing (every
    direction seen from at least `min_spread` apart), so such forecasts keep their values."""
    lam, vectors = np.linalg.eigh(np.asarray(information, np.float64))
    floor = np.sin(np.radians(float(min_spread_deg))) ** 2
    scale = np.minimum(1.0, np.clip(lam, 0.0, None) / floor) if floor > 0 else np.ones(3)
    if np.all(scale >= 1.0):
        return None
    return (vectors * scale) @ vectors.T


def suppress_unobserved(last_means: np.ndarray, means: np.ndarray, scaling: np.ndarray, rigid: bool) -> np.ndarray:
    """Forecast positions (G, T, 3) with each displacement from the last observed
    position (G, 3) scaled by `scaling`. A rigid group's moving members all take
    their centroid's correction, so the body stays rigid (its turn is seen
    across the rays); other groups' members are scaled one by one. Members the
    forecast keeps still stay still."""
    last = np.asarray(last_means, np.float64)
    pos = np.asarray(means, np.float64)
    removed = np.eye(3) - np.asarray(scaling, np.float64)
    displacement = pos - last[:, None]
    if not rigid:
        return pos - displacement @ removed.T
    moving = np.any(displacement != 0.0, axis=(1, 2))
    out = pos.copy()
    if moving.any():
        out[moving] -= (displacement[moving].mean(axis=0) @ removed.T)[None]
    return out
