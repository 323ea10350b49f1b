"""Small hand-made 4D scenes for the grouping tests.

`two_object_scene` builds a Model4D whose trajectories are known (canonical =
positions at the first step) with two objects moving differently, a
monocular camera circling them, and instance masks rendered by z-buffered
point splatting of the ground-truth points (independent of the Gaussian
rasterizer). `model_from_points` turns any (P,T,3) point trajectories with
instance labels (e.g. the synthetic scene's ground truth) into a Model4D.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mogaf.camera import project
from mogaf.grouping.core import MaskFrames
from mogaf.representation import GaussianSet, Model4D
from mogaf.scene import Instances


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV world-to-camera looking from eye to target."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ eye
    return T


def model_from_points(
    points: np.ndarray,
    labels: np.ndarray | None = None,
    num_bases: int = 4,
    seed: int = 0,
    coef_noise: float = 0.3,
    scale: float = 0.02,
    timesteps: np.ndarray | None = None,
) -> Model4D:
    """Model4D with trajectories = points (P,T,3), canonical = first step.

    Motion coefficient logits favour basis (label mod num_bases) with
    Gaussian noise, as a reconstruction of distinct motions would.
    """
    pts = np.asarray(points, dtype=np.float64)
    P, T = pts.shape[:2]
    rng = np.random.default_rng(seed)
    lab = np.zeros(P, np.int64) if labels is None else np.asarray(labels, np.int64)
    logits = rng.normal(0.0, coef_noise, (P, num_bases))
    logits[np.arange(P), lab % num_bases] += 3.0
    quats = np.zeros((P, 4))
    quats[:, 0] = 1.0
    fg = GaussianSet(
        means=pts[:, 0].copy(),
        quats=quats.copy(),
        log_scales=np.full((P, 3), np.log(scale)),
        opacity_logits=np.full(P, 3.0),
        color_logits=np.zeros((P, 3)),
    )
    rot6d = np.zeros((num_bases, T, 6))
    rot6d[..., 0] = 1.0
    rot6d[..., 4] = 1.0
    return Model4D(
        fg=fg,
        motion_coef_logits=logits,
        rot6d=rot6d,
        translations=np.zeros((num_bases, T, 3)),
        timesteps=np.arange(T, dtype=np.int64) if timesteps is None else np.asarray(timesteps, np.int64),
        trajectory_means=pts.copy(),
        trajectory_quats=np.repeat(quats[:, None], T, axis=1),
    )


def splat_instance_masks(
    points: np.ndarray, labels: np.ndarray, K: np.ndarray, w2c: np.ndarray, width: int, height: int, radius: int = 1
) -> np.ndarray:
    """(H,W) int32 instance mask: nearest point within `radius` px wins (z-buffer)."""
    uv, z = project(points, K, w2c)
    depth = np.full((height, width), np.inf)
    mask = np.zeros((height, width), np.int32)
    ok = z > 0
    col = np.floor(uv[:, 0]).astype(np.int64)
    row = np.floor(uv[:, 1]).astype(np.int64)
    order = np.argsort(-z)  # far first, near ones overwrite
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            r, c = row + dy, col + dx
            sel = ok & (r >= 0) & (r < height) & (c >= 0) & (c < width)
            idx = order[sel[order]]
            rr, cc, zz = r[idx], c[idx], z[idx]
            # Later (nearer) writes win within this offset; keep the nearest across offsets.
            closer = zz < depth[rr, cc]
            idx, rr, cc, zz = idx[closer], rr[closer], cc[closer], zz[closer]
            depth[rr, cc] = zz
            mask[rr, cc] = labels[idx]
    return mask


def sphere_points(n: int, radius: float, rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return radius * v / np.linalg.norm(v, axis=1, keepdims=True)


def box_points(n: int, size: float, rng: np.random.Generator) -> np.ndarray:
    p = rng.uniform(-size / 2, size / 2, (n, 3))
    face = rng.integers(0, 3, n)
    sign = rng.choice([-1.0, 1.0], n)
    p[np.arange(n), face] = sign * size / 2
    return p


@dataclass
class ToyScene:
    model: Model4D
    labels: np.ndarray  # (N,) GT object id per Gaussian (1, 2, ...)
    masks: np.ndarray  # (F,H,W) int32
    frames: MaskFrames
    instances: Instances
    width: int
    height: int


def two_object_scene(
    n_per_object: int = 800,
    T: int = 12,
    width: int = 64,
    height: int = 48,
    seed: int = 0,
    rigid_flags=(1, 1),
    close: bool = False,
) -> ToyScene:
    """A sphere translating and spinning, and a box tumbling the other way.

    close=True places the objects almost in contact (gap ~ 3 point spacings),
    so that only the motion features tell them apart along the seam.
    """
    rng = np.random.default_rng(seed)
    sphere = sphere_points(n_per_object, 0.45, rng)
    box = box_points(n_per_object, 0.8, rng)
    ca = np.array([-0.55 if close else -0.8, 0.0, 0.0])
    cb = np.array([0.46 if close else 0.8, 0.0, 0.0])
    traj = np.zeros((2 * n_per_object, T, 3))
    for t in range(T):
        s = t / max(T - 1, 1)
        traj[:n_per_object, t] = sphere @ _rot_z(1.2 * s).T + ca + np.array([0.0, 0.5 * s, 0.1 * s])
        traj[n_per_object:, t] = box @ (_rot_x(-1.0 * s) @ _rot_z(-0.6 * s)).T + cb + np.array([0.0, -0.4 * s, 0.0])
    labels = np.r_[np.ones(n_per_object, np.int64), np.full(n_per_object, 2, np.int64)]
    model = model_from_points(traj, labels, seed=seed)
    f = 0.9 * width
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    Ks, w2cs, masks = [], [], []
    for t in range(T):
        ang = -np.pi / 2 + 0.4 * t / max(T - 1, 1)
        eye = np.array([4.0 * np.cos(ang), 4.0 * np.sin(ang), 1.2])
        w2c = look_at(eye, np.zeros(3))
        Ks.append(K)
        w2cs.append(w2c)
        masks.append(splat_instance_masks(traj[:, t], labels, K, w2c, width, height, radius=1))
    frames = MaskFrames(K=np.stack(Ks), w2c=np.stack(w2cs), time_index=np.arange(T))
    inst = Instances(ids=[1, 2], names=["sphere", "box"], rigid=list(rigid_flags))
    return ToyScene(model, labels, np.stack(masks), frames, inst, width, height)
