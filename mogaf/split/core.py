"""The split: its roles, the Split record, and split.h5 (write_split / read_split)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..artefact import config_digest, read_artefact, write_artefact

SPLIT_STAGE = "split"
ROLES = ("observed", "evaluation", "evaluation_observed", "train_future")


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
