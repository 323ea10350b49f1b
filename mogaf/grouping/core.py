"""Shared pieces of the grouping stage: containers, seeding and the one
groups.h5 question the workflow asks (parameters: mogaf.grouping.params).

Paper references: main paper Sec. "Motion-aware Gaussian Grouping"
(Algorithm 1), supplementary "Details of Gaussian Grouping" (Algorithm 2:
naive 4D extension of Gaga, Algorithm 3: complete procedure) and
supplementary "Implementation Details / Motion-aware Gaussian Grouping".
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..artefact import open_artefact
from ..camera import project
from ..errors import MogafError

GROUP_STAGE = "group"


def has_rigid_groups(groups_h5: str | os.PathLike) -> bool:
    """Whether the rigid_init stage has anything to do. The workflow asks it
    while building the DAG, so it lives here, away from torch's import."""
    with open_artefact(groups_h5, GROUP_STAGE) as fh:
        rigid = np.asarray(fh["group_rigid"][()])
    return bool(np.any(rigid == 1))


@dataclass
class MaskFrames:
    """Cameras of the mask frames: K (F,3,3), w2c (F,4,4) OpenCV, and
    time_index (F,): the column of the model's trajectories (index into
    Model4D.timesteps) each frame was taken at."""

    K: np.ndarray
    w2c: np.ndarray
    time_index: np.ndarray

    def __post_init__(self) -> None:
        self.K = np.asarray(self.K, dtype=np.float64).reshape(-1, 3, 3)
        self.w2c = np.asarray(self.w2c, dtype=np.float64).reshape(-1, 4, 4)
        self.time_index = np.asarray(self.time_index, dtype=np.int64).reshape(-1)
        if not (len(self.K) == len(self.w2c) == len(self.time_index)):
            raise MogafError("grouping: mask frames need one K, w2c and time index each")

    def __len__(self) -> int:
        return int(self.time_index.size)


@dataclass
class InstanceTable:
    """Mask identities considered by the grouping (never background 0)."""

    ids: np.ndarray  # (J,) int64
    names: list[str]
    rigid: np.ndarray  # (J,) int8: 1 rigid, 0 non-rigid, -1 unknown
    rigid_source: list[str]  # where a known flag came from


@dataclass
class Groups:
    """The grouping of the N foreground Gaussians into K groups."""

    group_id: np.ndarray  # (N,) int64 in [0, K)
    rigid: np.ndarray  # (K,) int8
    static: np.ndarray  # (K,) int8
    instance_id: np.ndarray  # (K,) int64, mask identity (-1: none)
    names: list[str]
    rigid_source: list[str]  # "label" / "config" / "estimated"
    method: str
    params: dict[str, Any]
    diagnostics: dict[str, Any] = field(default_factory=dict)
    attrs: dict[str, Any] = field(default_factory=dict)

    @property
    def num_groups(self) -> int:
        return int(self.rigid.size)

    def members(self, k: int) -> np.ndarray:
        return np.flatnonzero(self.group_id == k)

    def sizes(self) -> np.ndarray:
        return np.bincount(self.group_id, minlength=self.num_groups).astype(np.int64)


# ---------------------------------------------------------------- seeding
def frames_in_time_order(time_index: np.ndarray) -> np.ndarray:
    """Frame indices sorted by time (stable: ties keep their order)."""
    return np.argsort(np.asarray(time_index), kind="stable")


def mask_gaussians(
    points: np.ndarray,
    mask: np.ndarray,
    K: np.ndarray,
    w2c: np.ndarray,
    instance_ids: np.ndarray,
    front_fraction: float = 1.0,
    num_patches: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """Gaussians whose projected centre falls inside each instance mask.

    points (N,3) are the deformed means at the mask's time; mask (H,W) holds
    instance ids (0 background). Only centres in front of the camera
    (z > 0) and inside the image count. Of these, per instance and per cell
    of a num_patches x num_patches image grid (Gaga's patch-wise front
    selection), the closest floor(front_fraction * n) (at least 1) along the
    view are kept: the "front Gaussians" that render the mask.

    Returns (gaussian_index (M,), instance_index (M,)) with instance_index
    indexing `instance_ids`, sorted by instance then Gaussian index.
    """
    mask = np.asarray(mask)
    H, W = mask.shape
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    if len(points) == 0 or len(instance_ids) == 0:
        return empty
    uv, z = project(points, K, w2c)
    ok = (z > 0) & np.all(np.isfinite(uv), axis=1)
    col = np.floor(np.where(ok, uv[:, 0], -1.0)).astype(np.int64)
    row = np.floor(np.where(ok, uv[:, 1], -1.0)).astype(np.int64)
    ok &= (col >= 0) & (col < W) & (row >= 0) & (row < H)
    g = np.flatnonzero(ok)
    if g.size == 0:
        return empty
    value = mask[row[g], col[g]]
    ids = np.asarray(instance_ids, dtype=np.int64)
    order = np.argsort(ids, kind="stable")
    pos = np.searchsorted(ids[order], value)
    pos = np.clip(pos, 0, len(ids) - 1)
    hit = ids[order][pos] == value
    hit &= value != 0
    g, inst = g[hit], order[pos[hit]]
    if g.size == 0:
        return empty
    if front_fraction < 1.0:
        P = max(int(num_patches), 1)
        ph, pw = -(-H // P), -(-W // P)
        cell = (row[g] // ph) * P + (col[g] // pw)
        key = inst.astype(np.int64) * (P * P) + cell
        srt = np.lexsort((g, z[g], key))  # by cell key, then depth, then index
        key_s = key[srt]
        starts = np.flatnonzero(np.r_[True, key_s[1:] != key_s[:-1]])
        counts = np.diff(np.r_[starts, key_s.size])
        rank = np.arange(key_s.size) - np.repeat(starts, counts)
        keep_n = np.maximum(np.floor(front_fraction * counts + 1e-9).astype(np.int64), 1)
        keep = rank < np.repeat(keep_n, counts)
        g, inst = g[srt][keep], inst[srt][keep]
    srt = np.lexsort((g, inst))
    return g[srt], inst[srt]
