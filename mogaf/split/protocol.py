"""The split protocols: which frames are observed, which are forecast targets (make_split).

See the mogaf.split package docstring for the iphone and dnerf protocols.
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import input_error
from ..scene import SPLIT_CODES
from .core import Split
from .params import check_ratio

MIN_OBSERVED_TIMESTEPS = 3


def _observed_step_count(scene_time_grid: np.ndarray, ratio: float, protocol: str, T: int) -> int:
    if protocol == "iphone":
        # t < r*T, with a tolerance so that 0.6*60 = 36 exactly gives 36 steps.
        return int(np.sum(np.arange(T) < ratio * T - 1e-9))
    return int(np.sum(scene_time_grid < ratio - 1e-9))


def make_split(
    scene_time: np.ndarray,
    time_index: np.ndarray,
    num_timesteps: int,
    source_split: np.ndarray,
    camera_id: np.ndarray,
    layout: str,
    ratio: float,
    source: str | os.PathLike = "scene",
) -> Split:
    """Build the split from per-frame metadata only (no pixels are read)."""
    r = check_ratio(ratio)
    T = int(num_timesteps)
    steps = np.asarray(time_index)
    if steps.size and (steps.min() < 0 or steps.max() >= T):
        raise input_error(
            source,
            f"frame time steps {int(steps.min())}..{int(steps.max())} lie outside the scene's "
            f"{T} time steps (rerun ingest)",
        )
    grid = np.arange(T) / max(T - 1, 1)
    protocol = "iphone" if layout == "iphone" else "dnerf"
    T_obs = _observed_step_count(grid, r, protocol, T)
    if T_obs < MIN_OBSERVED_TIMESTEPS:
        raise input_error(
            source, f"ratio {r} leaves {T_obs} observed time steps; at least {MIN_OBSERVED_TIMESTEPS} are needed"
        )
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
        raise input_error(
            source,
            f"the {frame_ids['observed'].size} training frame(s) before the cut at ratio {r} are "
            f"all at time step {int(seen[0])} of the {T_obs} observed steps; at least two "
            "observed time steps need a training frame (a larger ratio may give them)",
        )
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
