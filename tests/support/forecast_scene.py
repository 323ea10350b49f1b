"""Forecast-stage inputs with known motion, written with the library's own writers.

A scene.h5 of tiny blank frames (T = 8 time steps, RATIO 0.5: steps 0-3
observed, 4-7 forecast) with ground-truth 3D points riding on the rigid
group, its split.h5, and a refine-stage model whose N = 30 foreground
Gaussians have known trajectories, in three groups of N_PER:
  STATIC    never move
  RIGID     one common constant velocity (RIGID_VELOCITY)
  NONRIGID  each its own constant velocity and a fixed random orientation
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mogaf.artefact import write_artefact
from mogaf.camera import project
from mogaf.grouping.core import Groups
from mogaf.representation import GaussianSet, Model4D, save_model
from mogaf.scene import SPLIT_CODES, Scene, save_scene
from mogaf.split import split_scene, write_split

T, RATIO = 8, 0.5
T_OBS = 4
N_PER = 10
N = 3 * N_PER
STATIC, RIGID, NONRIGID = 0, 1, 2
RIGID_VELOCITY = np.array([0.1, 0.05, -0.02])


def members(k: int) -> np.ndarray:
    return np.arange(k * N_PER, (k + 1) * N_PER)


def world(seed: int = 0):
    """Positions (N, T, 3) and orientations (N, 4) over the full time grid."""
    rng = np.random.default_rng(seed)
    centres = np.array([[-5.0, 0.0, 0.0], [0.0, 0.0, 0.0], [5.0, 0.0, 0.0]])
    start = np.concatenate([c + rng.uniform(-0.3, 0.3, size=(N_PER, 3)) for c in centres])
    velocity = np.zeros((N, 3))
    velocity[members(RIGID)] = RIGID_VELOCITY
    velocity[members(NONRIGID)] = rng.uniform(-0.2, 0.2, size=(N_PER, 3))
    pos = start[:, None, :] + velocity[:, None, :] * np.arange(T)[None, :, None]
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (N, 1))
    q = rng.normal(size=(N_PER, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    quats[members(NONRIGID)] = q * np.sign(q[:, :1])
    return pos, quats, velocity


def _camera(cam: int) -> tuple[np.ndarray, np.ndarray]:
    """K and w2c of camera `cam` (0: the training camera, 1: the held-out one), the same at every step."""
    w2c = np.eye(4)
    w2c[:3, 3] = [0.1 * cam, 0.0, 10.0]
    return np.array([[10.0, 0, 2], [0, 10.0, 2], [0, 0, 1]]), w2c


def write_scene(
    folder: Path, *, with_gt: bool, still_gt: bool = False, tracks2d: bool = False, no_train_frame_at: int = -1
) -> tuple[Path, Path]:
    """scene.h5 and split.h5 of world(); `with_gt`: ground-truth points riding
    the rigid group, `still_gt`: and points resting on the static group,
    `tracks2d`: and their 2D tracks in the training camera (0), visible at
    every step; `no_train_frame_at`: a time step the training camera has no frame of."""
    pos, _, _ = world()
    names, K, w2c, time, tidx, cams, splits = [], [], [], [], [], [], []
    for t in range(T):
        for cam in (0, 1):
            if cam == 0 and t == no_train_frame_at:
                continue
            names.append(f"{cam}_{t:05d}")
            K.append(_camera(cam)[0])
            w2c.append(_camera(cam)[1])
            time.append(t / (T - 1))
            tidx.append(t)
            cams.append(cam)
            splits.append(SPLIT_CODES["train"] if cam == 0 else SPLIT_CODES["val"])
    F = len(names)
    gt = {}
    if with_gt:
        # surface points riding exactly on the rigid group's Gaussians
        gt = {"points3d": pos[members(RIGID)].astype(np.float64) + np.array([0.01, 0.0, 0.0])}
        if still_gt:
            resting = pos[members(STATIC)].astype(np.float64) + np.array([0.0, 0.01, 0.0])
            gt["points3d"] = np.concatenate([gt["points3d"], resting])
        if tracks2d:
            P = gt["points3d"].shape[0]
            gt["tracks2d"] = np.stack([project(gt["points3d"][:, t], *_camera(0))[0] for t in range(T)], axis=1)
            gt["visible"] = np.ones((P, T), bool)
    scene = Scene(
        dataset="test",
        name="fc",
        layout="iphone",
        frame_names=names,
        images=np.zeros((F, 4, 4, 3), np.uint8),
        K=np.array(K),
        w2c=np.array(w2c),
        time=np.array(time),
        time_index=np.array(tidx),
        num_timesteps=T,
        camera_id=np.array(cams),
        source_split=np.array(splits, np.int8),
        ground_truth=gt,
        meta={"background": [1.0, 1.0, 1.0]},
    )
    folder.mkdir(parents=True, exist_ok=True)
    scene_h5 = save_scene(folder / "scene.h5", scene, config_digest="fc-test")
    split_h5 = write_split(folder / "split.h5", split_scene(scene_h5, RATIO))
    return scene_h5, split_h5


def write_priors(
    path: Path,
    scene_h5: Path,
    split_h5: Path,
    xy: np.ndarray | None = None,
    visible: np.ndarray | None = None,
    reverse: bool = False,
    step_shift: int = 0,
) -> Path:
    """A priors.h5 over the split's observed frames: their ids and time steps,
    and 2D tracks (N, frames, 2) with their visibility (none by default);
    `reverse`: the frames stored last first; `step_shift`: time steps off by this."""
    from mogaf.split import load_frames, read_split

    split = read_split(split_h5)
    frames = load_frames(scene_h5, split, "observed")
    F = len(split.frame_ids["observed"])
    xy = np.zeros((0, F, 2), np.float32) if xy is None else np.asarray(xy, np.float32)
    visible = np.ones(xy.shape[:2], np.uint8) if visible is None else np.asarray(visible, np.uint8)
    n = xy.shape[0]
    order = np.arange(F)[::-1] if reverse else np.arange(F)
    data = {
        "frame_ids": np.asarray(split.frame_ids["observed"], np.int64)[order],
        "timesteps": np.asarray(frames.time_index, np.int64)[order] + int(step_shift),
        "tracks": {
            "query_index": np.zeros(n, np.int64),
            "xy": xy[:, order],
            "visible": visible[:, order],
            "confidence": np.ones(xy.shape[:2], np.float32),
        },
    }
    return write_artefact(path, "priors", data, config_digest="fc-test")


def write_model(path: Path, observed_timesteps: np.ndarray, last_step_shift: float = 0.0) -> Path:
    """The world's fg Gaussians moving as in world(); `last_step_shift` moves
    them along x at the last observed step only (a reconstruction's end error)."""
    pos, quats, _ = world()
    steps = np.asarray(observed_timesteps)
    Tm = steps.size
    traj = pos[:, steps].copy()
    traj[:, -1, 0] += last_step_shift
    rng = np.random.default_rng(1)
    fg = GaussianSet(
        means=pos[:, 0].astype(np.float32),
        quats=quats.astype(np.float32),
        log_scales=np.full((N, 3), -3.0, np.float32),
        opacity_logits=np.zeros(N, np.float32),
        color_logits=rng.normal(size=(N, 3)).astype(np.float32),
    )
    model = Model4D(
        fg=fg,
        motion_coef_logits=np.zeros((N, 1), np.float32),
        rot6d=np.tile(np.array([1.0, 0, 0, 0, 1, 0], np.float32), (1, Tm, 1)),
        translations=np.zeros((1, Tm, 3), np.float32),
        timesteps=steps.astype(np.int64),
        trajectory_means=traj.astype(np.float32),
        trajectory_quats=np.repeat(quats[:, None], Tm, axis=1).astype(np.float32),
    )
    return save_model(path, "refine", model, config_digest="fc-test")


def groups_of(group_id: np.ndarray, static: list[int], rigid: list[int]) -> Groups:
    """A grouping of the model's Gaussians: group_id per Gaussian, a static and a rigid flag per group."""
    K = len(static)
    return Groups(
        group_id=np.asarray(group_id, np.int64),
        rigid=np.asarray(rigid, np.int8),
        static=np.asarray(static, np.int8),
        instance_id=-np.ones(K, np.int64),
        names=[f"g{k}" for k in range(K)],
        rigid_source=["config"] * K,
        method="ours",
        params={"seed": 0},
    )
