"""Reading a split's data from scene.h5: the frames of a role, and ground truth cut in time."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from ..artefact import open_artefact, read_dataset, read_tree, time_steps_index
from ..errors import MogafError, input_error
from ..scene import SCENE_STAGE, Scene, load_scene
from .core import ROLES, Split, read_split


def load_frames(scene_h5: str | os.PathLike, split: Split | str | os.PathLike, role: str) -> Scene:
    """The frames of one role, read from scene.h5 row by row (nothing else).

    Shipped priors and ground truth are not loaded here: use
    `load_observed_shipped` / `load_ground_truth`, which cut the time axis.
    """
    if role not in ROLES:
        raise ValueError(f"unknown split role {role!r}; expected one of {ROLES}")
    sp = split if isinstance(split, Split) else read_split(split)
    frames = load_scene(scene_h5, sp.frame_ids[role])
    # A split made for another scene would hand an observed role future frames.
    if frames.num_timesteps != sp.num_timesteps:
        raise input_error(
            scene_h5,
            f"has {frames.num_timesteps} time steps, the split has {sp.num_timesteps}: "
            "the split was made for another scene",
        )
    check_role_steps(scene_h5, sp, role, frames.time_index)
    return frames


def check_role_steps(scene_h5: str | os.PathLike, split: Split, role: str, time_index: np.ndarray) -> None:
    """The time steps (scene.h5's frames/time_index) of the split's frames of
    `role`, in its order, must be the role's own (observed or forecast) steps;
    otherwise the split was made for another scene."""
    steps = split.observed_timesteps if role in ("observed", "evaluation_observed") else split.forecast_timesteps
    outside = ~np.isin(time_index, steps)
    if outside.any():
        f = int(np.flatnonzero(outside)[0])
        raise input_error(
            scene_h5,
            f"frame {int(split.frame_ids[role][f])} of split role '{role}' is at time step "
            f"{int(time_index[f])}, outside the role's steps: the split was made for another scene",
        )


def evenly_spaced_frame_ids(split: Split, role: str, limit: int) -> np.ndarray:
    """Scene frame ids of at most `limit` frames of `role`, evenly spaced over it (0: all of them)."""
    ids = np.asarray(split.frame_ids[role], np.int64)
    if 0 < limit < ids.size:
        ids = ids[np.unique(np.round(np.linspace(0, ids.size - 1, limit)).astype(np.int64))]
    return ids


def load_evenly_spaced_frames(scene_h5: str | os.PathLike, split: Split, role: str, limit: int) -> Scene:
    """The frames `evenly_spaced_frame_ids` picks."""
    ids = evenly_spaced_frame_ids(split, role, limit)
    return load_frames(scene_h5, dataclasses.replace(split, frame_ids={**split.frame_ids, role: ids}), role)


# Time axes of ground-truth arrays written by the synthetic generator.
GROUND_TRUTH_TIME_AXES = {"points3d": 1, "tracks2d": 1, "visible": 1, "object_poses": 1}


def load_ground_truth(
    scene_h5: str | os.PathLike, split: Split, part: str, entries: Iterable[str] | None = None
) -> dict[str, Any]:
    """Ground truth restricted to the observed or the forecast time steps
    (only `entries` of it, if given; absent ones are left out).

    Only the evaluation stage may ask for part="forecast".
    """
    if part not in ("observed", "forecast"):
        raise ValueError("part must be 'observed' or 'forecast'")
    steps = split.observed_timesteps if part == "observed" else split.forecast_timesteps
    T = int(split.num_timesteps)
    try:
        on_time_axis = time_steps_index(steps, T)  # only the asked steps come off disk
    except MogafError as exc:
        raise MogafError(f"load_ground_truth: the split's {exc}") from None

    def selection(key: str, ds: h5py.Dataset) -> Any:
        axis = GROUND_TRUTH_TIME_AXES.get(key)
        if axis is None:
            return None
        if ds.ndim <= axis or ds.shape[axis] != T:
            raise input_error(
                scene_h5, f"ground-truth entry '{key}' has shape {ds.shape}, expected {T} time steps on axis {axis}"
            )
        return (slice(None),) * axis + (on_time_axis,)

    with open_artefact(scene_h5, SCENE_STAGE) as fh:
        if int(fh.attrs["num_timesteps"]) != T:
            raise input_error(
                scene_h5,
                f"has {int(fh.attrs['num_timesteps'])} time steps, the split has {T}: "
                "the split was made for another scene",
            )
        if "ground_truth" not in fh:
            return {}
        g = fh["ground_truth"]
        if entries is None:
            return read_tree(g, Path(scene_h5), prefix="ground_truth/", selection=selection)
        return {
            key: read_dataset(g[key], Path(scene_h5), f"ground_truth/{key}", selection(key, g[key]))
            for key in entries
            if key in g and isinstance(g[key], h5py.Dataset)
        }
