"""The forecast split: made once, here; every later stage reads only its frames.

Protocols
- iphone (DyCheck layout, incl. the synthetic scene): T time steps; observed
  = train-camera frames with t < r*T; evaluation = held-out (val) frames with
  t >= r*T; held-out frames with t < r*T measure reconstruction quality.
- dnerf (GaussianPrediction's protocol): frames of transforms_train with
  time < r are observed; frames of transforms_train and transforms_test with
  time >= r are forecast targets; test frames with time < r measure
  reconstruction quality. Validation frames are not used.

split.h5 holds frame ids (rows of scene.h5) per role and the time steps:
observed_timesteps = 0 .. T_obs-1 (the grid steps before the cut) and
forecast_timesteps = T_obs .. T-1.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from .artefact import (config_digest, open_artefact, read_artefact, read_dataset, read_rows, read_tree,
                       time_steps_index, write_artefact)
from .errors import MogafError, input_error
from .scene import SCENE_STAGE, SPLIT_CODES, Scene, check_scene_file, load_scene

SPLIT_STAGE = "split"
ROLES = ("observed", "evaluation", "evaluation_observed", "train_future")
MIN_OBSERVED_TIMESTEPS = 3


@dataclass
class Split:
    ratio: float
    protocol: str
    num_timesteps: int
    observed_timesteps: np.ndarray  # (T_obs,) int64
    forecast_timesteps: np.ndarray  # (T_fc,) int64
    frame_ids: dict[str, np.ndarray]  # role -> rows of scene.h5

    @property
    def num_observed_timesteps(self) -> int:
        return int(self.observed_timesteps.size)


def check_ratio(ratio: float) -> float:
    r = float(ratio)
    if not np.isfinite(r) or not (0.0 < r < 1.0):
        raise MogafError(f"observation ratio {ratio!r} is outside (0, 1)")
    return r


def _observed_step_count(scene_time_grid: np.ndarray, ratio: float, protocol: str, T: int) -> int:
    if protocol == "iphone":
        # t < r*T, with a tolerance so that 0.6*60 = 36 exactly gives 36 steps.
        return int(np.sum(np.arange(T) < ratio * T - 1e-9))
    return int(np.sum(scene_time_grid < ratio - 1e-9))


def make_split(scene_time: np.ndarray, time_index: np.ndarray, num_timesteps: int, source_split: np.ndarray,
               camera_id: np.ndarray, layout: str, ratio: float, source: str | os.PathLike = "scene") -> Split:
    """Build the split from per-frame metadata only (no pixels are read)."""
    r = check_ratio(ratio)
    T = int(num_timesteps)
    steps = np.asarray(time_index)
    if steps.size and (steps.min() < 0 or steps.max() >= T):
        raise input_error(source, f"frame time steps {int(steps.min())}..{int(steps.max())} lie outside the scene's "
                                  f"{T} time steps (rerun ingest)")
    grid = np.arange(T) / max(T - 1, 1)
    protocol = "iphone" if layout == "iphone" else "dnerf"
    T_obs = _observed_step_count(grid, r, protocol, T)
    if T_obs < MIN_OBSERVED_TIMESTEPS:
        raise input_error(source, f"ratio {r} leaves {T_obs} observed time steps; at least {MIN_OBSERVED_TIMESTEPS} are needed")
    if T_obs >= T:
        raise input_error(source, f"ratio {r} leaves no time step to forecast ({T} steps in the scene)")
    is_past = np.asarray(time_index) < T_obs
    train = np.asarray(source_split) == SPLIT_CODES["train"]
    val = np.asarray(source_split) == SPLIT_CODES["val"]
    test = np.asarray(source_split) == SPLIT_CODES["test"]
    if protocol == "iphone":
        held_out = val
        future_targets = held_out & ~is_past
    else:
        held_out = test
        future_targets = (train | test) & ~is_past
    frame_ids = {
        "observed": np.flatnonzero(train & is_past),
        "evaluation": np.flatnonzero(future_targets),
        "evaluation_observed": np.flatnonzero(held_out & is_past),
        "train_future": np.flatnonzero(train & ~is_past),
    }
    if frame_ids["observed"].size == 0:
        raise input_error(source, f"no training frame before the cut at ratio {r}")
    seen = np.unique(np.asarray(time_index)[frame_ids["observed"]])
    if seen.size < 2:
        # the observed steps would all be filled in from one instant: motion invented, not learnt
        raise input_error(source, f"the {frame_ids['observed'].size} training frame(s) before the cut at ratio {r} are "
                                  f"all at time step {int(seen[0])} of the {T_obs} observed steps; at least two "
                                  "observed time steps need a training frame (a larger ratio may give them)")
    if frame_ids["evaluation"].size == 0:
        raise input_error(source, f"no evaluation frame after the cut at ratio {r}")
    return Split(
        ratio=r,
        protocol=protocol,
        num_timesteps=T,
        observed_timesteps=np.arange(T_obs, dtype=np.int64),
        forecast_timesteps=np.arange(T_obs, T, dtype=np.int64),
        frame_ids={k: v.astype(np.int64) for k, v in frame_ids.items()},
    )


def split_scene(scene_h5: str | os.PathLike, ratio: float) -> Split:
    """Read per-frame metadata of scene.h5 (no images) and build the split."""
    with open_artefact(scene_h5, SCENE_STAGE) as fh:
        n, T = check_scene_file(fh, scene_h5)
        rows = np.arange(n)
        meta = {k: read_rows(fh, f"frames/{k}", rows) for k in ("time", "time_index", "source_split", "camera_id")}
        layout = fh.attrs["layout"]
        layout = layout.decode() if isinstance(layout, bytes) else str(layout)
    return make_split(meta["time"], meta["time_index"], T, meta["source_split"], meta["camera_id"], layout, ratio, scene_h5)


def write_split(path: str | os.PathLike, split: Split, *, digest: str | None = None) -> Path:
    data = {
        "observed_timesteps": split.observed_timesteps,
        "forecast_timesteps": split.forecast_timesteps,
        "frame_ids": dict(split.frame_ids),
    }
    attrs = {"ratio": split.ratio, "protocol": split.protocol, "num_timesteps": split.num_timesteps}
    digest = digest or config_digest({"ratio": split.ratio, "protocol": split.protocol})
    return write_artefact(path, SPLIT_STAGE, data, config_digest=digest, attrs=attrs)


def read_split(path: str | os.PathLike) -> Split:
    art = read_artefact(path, SPLIT_STAGE, required=["observed_timesteps", "forecast_timesteps", "frame_ids/observed"])
    return Split(
        ratio=float(art.attrs["ratio"]),
        protocol=str(art.attrs["protocol"]),
        num_timesteps=int(art.attrs["num_timesteps"]),
        observed_timesteps=np.asarray(art["observed_timesteps"], dtype=np.int64),
        forecast_timesteps=np.asarray(art["forecast_timesteps"], dtype=np.int64),
        frame_ids={k: np.asarray(v, dtype=np.int64) for k, v in art["frame_ids"].items()},
    )


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
        raise input_error(scene_h5, f"has {frames.num_timesteps} time steps, the split has {sp.num_timesteps}: "
                                    "the split was made for another scene")
    steps = sp.observed_timesteps if role in ("observed", "evaluation_observed") else sp.forecast_timesteps
    outside = ~np.isin(frames.time_index, steps)
    if outside.any():
        f = int(np.flatnonzero(outside)[0])
        raise input_error(scene_h5, f"frame {int(sp.frame_ids[role][f])} of split role '{role}' is at time step "
                                    f"{int(frames.time_index[f])}, outside the role's steps: the split was made for another scene")
    return frames


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


def load_ground_truth(scene_h5: str | os.PathLike, split: Split, part: str,
                      entries: Iterable[str] | None = None) -> dict[str, Any]:
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
            raise input_error(scene_h5, f"ground-truth entry '{key}' has shape {ds.shape}, expected {T} time steps on axis {axis}")
        return (slice(None),) * axis + (on_time_axis,)

    with open_artefact(scene_h5, SCENE_STAGE) as fh:
        if int(fh.attrs["num_timesteps"]) != T:
            raise input_error(scene_h5, f"has {int(fh.attrs['num_timesteps'])} time steps, the split has {T}: "
                                        "the split was made for another scene")
        if "ground_truth" not in fh:
            return {}
        g = fh["ground_truth"]
        if entries is None:
            return read_tree(g, Path(scene_h5), prefix="ground_truth/", selection=selection)
        return {key: read_dataset(g[key], Path(scene_h5), f"ground_truth/{key}", selection(key, g[key]))
                for key in entries if key in g and isinstance(g[key], h5py.Dataset)}
