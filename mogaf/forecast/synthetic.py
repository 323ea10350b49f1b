"""Procedural ground-truth trajectory sets, (G, T_total, 7) float64 each.

Used by `python -m mogaf.bench forecast` and the tests. Time is the frame
index on a uniform grid; lengths are scene units (objects ~1 unit across).
Orientations co-rotate with the material (rigid sets) or follow the surface
frame (sheet), so they are meaningful rotations, not noise.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from mogaf.forecast import quat


def _random_quats(rng: np.random.Generator, n: int) -> np.ndarray:
    return quat.canonical_sign(quat.normalize(rng.normal(size=(n, 4))))


def rigid_motion(
    points: np.ndarray, q0: np.ndarray, centre: np.ndarray, rot: np.ndarray, trans: np.ndarray
) -> np.ndarray:
    """Apply per-frame rigid transforms (rotation rot[t] (T,4) about `centre`,
    then translation trans[t] (T,3)) to points (G,3) with orientations q0 (G,4)."""
    g, t = points.shape[0], rot.shape[0]
    out = np.empty((g, t, 7))
    rel = points - centre
    for k in range(t):
        out[:, k, :3] = centre + quat.rotate(rot[k][None], rel) + trans[k]
        out[:, k, 3:] = quat.mul(rot[k][None], q0)
    return out


def rigid_box(n_gaussians: int = 2000, n_frames: int = 60, seed: int = 0) -> np.ndarray:
    """A box translating at constant velocity while spinning at a constant rate
    about a tilted axis through its centre (a uniform screw-free twist)."""
    rng = np.random.default_rng(seed)
    half = np.array([0.5, 0.3, 0.2])
    pts = rng.uniform(-1.0, 1.0, size=(n_gaussians, 3)) * half
    q0 = _random_quats(rng, n_gaussians)
    t = np.arange(n_frames, dtype=np.float64)
    axis = np.array([0.3, 0.2, 1.0])
    rot = quat.from_axis_angle(np.broadcast_to(axis, (n_frames, 3)), t * (2.0 * np.pi / 48.0))
    trans = t[:, None] * np.array([0.03, 0.01, 0.0])
    return rigid_motion(pts, q0, np.zeros(3), rot, trans)


def ballistic_sphere(n_gaussians: int = 2000, n_frames: int = 60, seed: int = 1) -> np.ndarray:
    """A spinning sphere thrown upwards: parabolic centre (constant gravity),
    constant spin about a fixed axis."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n_gaussians, 3))
    pts = 0.3 * d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.7, 1.0, size=(n_gaussians, 1))
    q0 = _random_quats(rng, n_gaussians)
    t = np.arange(n_frames, dtype=np.float64)
    v0 = np.array([0.04, 0.0, 0.09])
    gvec = np.array([0.0, 0.0, -0.003])
    trans = t[:, None] * v0 + 0.5 * t[:, None] ** 2 * gvec
    rot = quat.from_axis_angle(np.broadcast_to(np.array([1.0, 0.5, 0.0]), (n_frames, 3)), t * 0.08)
    return rigid_motion(pts, q0, np.zeros(3), rot, trans)


def waving_sheet(n_gaussians: int = 2000, n_frames: int = 60, seed: int = 2) -> np.ndarray:
    """A cloth-like sheet pinned along x = 0 with a travelling wave whose
    amplitude grows away from the pin: z = A x sin(k x - w t). Orientations
    follow the local surface frame (tangent along x, normal)."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.0, 1.0, size=n_gaussians)
    y = rng.uniform(-0.5, 0.5, size=n_gaussians)
    t = np.arange(n_frames, dtype=np.float64)
    amp, k, w = 0.25, 2.0 * np.pi / 0.8, 2.0 * np.pi / 30.0
    phase = k * x[:, None] - w * t[None, :]
    z = amp * x[:, None] * np.sin(phase)
    dzdx = amp * np.sin(phase) + amp * x[:, None] * k * np.cos(phase)
    out = np.empty((n_gaussians, n_frames, 7))
    out[..., 0] = x[:, None]
    out[..., 1] = y[:, None]
    out[..., 2] = z
    # Rotation about +y taking +x onto the tangent (1, 0, dz/dx).
    ang = -np.arctan(dzdx)
    qy = quat.from_axis_angle(np.broadcast_to(np.array([0.0, 1.0, 0.0]), ang.shape + (3,)), ang)
    q0 = _random_quats(rng, n_gaussians)
    out[..., 3:] = quat.mul(qy, q0[:, None, :])
    return out


def static_cloud(n_gaussians: int = 2000, n_frames: int = 60, seed: int = 3) -> np.ndarray:
    """Nothing moves."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-0.5, 0.5, size=(n_gaussians, 3))
    q0 = _random_quats(rng, n_gaussians)
    out = np.empty((n_gaussians, n_frames, 7))
    out[..., :3] = pts[:, None]
    out[..., 3:] = q0[:, None]
    return out


TRAJECTORY_SETS: dict[str, Callable[..., np.ndarray]] = {
    "rigid_box": rigid_box,
    "ballistic_sphere": ballistic_sphere,
    "waving_sheet": waving_sheet,
    "static": static_cloud,
}


# --- stress trajectories (numerical-stability tests) -------------------------


def spin_near_pi(n_gaussians: int = 64, n_frames: int = 24, seed: int = 4, angle: float = 0.97 * np.pi) -> np.ndarray:
    """A rigid body spinning by `angle` (close to pi) per frame about a tilted
    axis: consecutive quaternions are nearly orthogonal."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-0.5, 0.5, size=(n_gaussians, 3))
    q0 = _random_quats(rng, n_gaussians)
    t = np.arange(n_frames, dtype=np.float64)
    rot = quat.from_axis_angle(np.broadcast_to(np.array([0.2, -0.4, 1.0]), (n_frames, 3)), t * angle)
    return rigid_motion(pts, q0, np.array([0.1, 0.0, 0.0]), rot, np.zeros((n_frames, 3)))


def high_freq_oscillation(n_gaussians: int = 64, n_frames: int = 24, seed: int = 5, period: float = 2.5) -> np.ndarray:
    """Every Gaussian shakes along its own direction with a 2.5-frame period
    while its orientation wobbles by +-0.8 rad at the same frequency."""
    rng = np.random.default_rng(seed)
    base = rng.uniform(-0.5, 0.5, size=(n_gaussians, 3))
    dirs = rng.normal(size=(n_gaussians, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    q0 = _random_quats(rng, n_gaussians)
    t = np.arange(n_frames, dtype=np.float64)
    s = np.sin(2.0 * np.pi * t / period)
    out = np.empty((n_gaussians, n_frames, 7))
    out[..., :3] = base[:, None] + 0.3 * s[None, :, None] * dirs[:, None]
    wob = quat.from_axis_angle(
        np.broadcast_to(dirs[:, None], (n_gaussians, n_frames, 3)), 0.8 * s[None, :] * np.ones((n_gaussians, 1))
    )
    out[..., 3:] = quat.mul(wob, q0[:, None])
    return out


def bounce_stop(n_gaussians: int = 64, n_frames: int = 24, seed: int = 6, impact: int | None = None) -> np.ndarray:
    """A falling ball that hits the ground at frame `impact` (default: 3 frames
    before the end) and stops dead: an abrupt change right before the
    forecast starts."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n_gaussians, 3))
    pts = 0.2 * d / np.linalg.norm(d, axis=1, keepdims=True)
    q0 = _random_quats(rng, n_gaussians)
    impact = n_frames - 3 if impact is None else impact
    t = np.arange(n_frames, dtype=np.float64)
    tc = np.minimum(t, impact)
    height = 1.0 - 0.5 * 0.004 * tc**2 - 0.02 * tc
    trans = np.stack([0.01 * tc, np.zeros_like(tc), height], axis=1)
    rot = quat.from_axis_angle(np.broadcast_to(np.array([0.0, 1.0, 0.0]), (n_frames, 3)), 0.1 * tc)
    return rigid_motion(pts, q0, np.zeros(3), rot, trans)


def add_noise(traj: np.ndarray, pos_sigma: float = 0.01, rot_sigma: float = 0.02, seed: int = 7) -> np.ndarray:
    """Gaussian noise on positions and on the quaternion (renormalised)."""
    rng = np.random.default_rng(seed)
    out = np.array(traj, dtype=np.float64, copy=True)
    out[..., :3] += rng.normal(scale=pos_sigma, size=out[..., :3].shape)
    out[..., 3:] = quat.normalize(out[..., 3:] + rng.normal(scale=rot_sigma, size=out[..., 3:].shape))
    return out
