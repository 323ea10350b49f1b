"""A group's observed motion in the form the structured MoGaF forecaster's
candidates forecast (GroupMotion), and back from a forecast trajectory to
every member's poses."""

from __future__ import annotations

import numpy as np

from mogaf.forecast import quat
from mogaf.forecast.classical import constant_twist_rollout
from mogaf.forecast.trajectory import (
    accumulated_rotvec,
    braking_polynomial,
    integrate_rotvec,
    local_polynomial,
    rigid_decomposition,
    rigid_group_still,
    still_gaussians,
)


class GroupMotion:
    """A group's observed motion in the form the candidates forecast.

    rigid: one trajectory (centroids (T, 3), accumulated rotation vectors
    (T, 3)) of the whole group, carried to its moving members. Non-rigid:
    every moving Gaussian's position (3) and accumulated rotation vector (3).
    In both, still Gaussians keep their last pose in every candidate
    (`moving` indexes the others)."""

    def __init__(
        self,
        obs: np.ndarray,
        rigid: bool,
        still_factor: float,
        decomposition: tuple[np.ndarray, np.ndarray, float] | None = None,
        damping: float = 0.0,
    ) -> None:
        """`decomposition`: rigid_decomposition(obs[..., :3]) when already computed.
        `damping` (structured.damping): the forecast's speed halves every
        damping x T frames (T observed); 0 = undamped."""
        self.obs = obs
        self.damping = damping
        self.rigid = rigid
        self.last = obs[:, -1]
        pos = obs[..., :3]
        if rigid:
            self.centroids, self.rotations, _ = decomposition or rigid_decomposition(pos)
            # A still part the grouping joined to a moving body (a hinge's base,
            # a resting object it touched) keeps its last pose; the body's motion
            # is still the whole group's fit, not the moving members' alone.
            self.still = rigid_group_still(pos, still_factor)
            self.moving = np.flatnonzero(~self.still)
            radius = float(np.sqrt(np.mean(np.sum((pos[:, -1] - self.centroids[-1]) ** 2, axis=-1))))
            # (6, T): centroid xyz, accumulated body rotation vector xyz
            self.series = np.concatenate([self.centroids.T, accumulated_rotvec(self.rotations).T], axis=0)
            self.floor = np.array([1e-3 * max(radius, 1e-6)] * 3 + [1e-3] * 3)
        else:
            self.still = still_gaussians(pos, still_factor, obs[..., 3:])
            moving = ~self.still
            self.moving = np.flatnonzero(moving)
            m = obs[moving]
            extent = (
                float(np.sqrt(np.mean(np.sum((pos[:, -1] - pos[:, -1].mean(0)) ** 2, axis=-1))))
                if obs.shape[0] > 1
                else 1.0
            )
            rv = accumulated_rotvec(m[..., 3:])
            # (6 * G_moving, T): for each moving Gaussian x, y, z, then its rotation vector
            self.series = np.concatenate([m[..., :3], rv], axis=-1).transpose(0, 2, 1).reshape(-1, obs.shape[1])
            self.floor = np.tile(np.array([1e-3 * max(extent, 1e-6)] * 3 + [1e-3] * 3), len(self.moving))

    # A candidate's trajectory: rigid, the group pose (n, 7) -- centroid and
    # rotation from the last frame, x_t = g_t (x - c_T) + c_t; non-rigid, the
    # moving Gaussians' poses (M, n, 7). members() carries it to all G.
    def frozen_trajectory(self, n: int) -> np.ndarray:
        if self.rigid:
            pose = np.concatenate([self.centroids[-1], [1.0, 0.0, 0.0, 0.0]])
            return np.repeat(pose[None], n, axis=0)
        return np.repeat(self.last[self.moving, None, :], n, axis=1)

    def constant_velocity_trajectory(self, n: int) -> np.ndarray:
        """Constant twist of the group (rigid) or of each moving Gaussian."""
        if self.rigid:
            prev = np.concatenate([self.centroids[-2], self.rotations[-2]])[None]
            last = np.concatenate([self.centroids[-1], self.rotations[-1]])[None]
            # (the decomposition's rotations are the identity at the last frame,
            # so the twist's rotations are already relative to it)
            return constant_twist_rollout(prev, last, n)[0]
        m = self.obs[self.moving]
        return constant_twist_rollout(m[:, -2], m[:, -1], n)

    def polynomial_trajectory(self, n: int, window: int, degree: int) -> np.ndarray:
        """Each series' least-squares polynomial through its last `window`
        values (rigid: the group's centroid and accumulated rotation vector):
        degree 1 is the linear_trend candidate, 2 constant_acceleration."""
        if not len(self.moving):
            return self.frozen_trajectory(n)
        return self.series_trajectory(local_polynomial(self.series, window, degree, n))

    def braking_trajectory(self, n: int, window: int) -> np.ndarray:
        """The braking candidate: each vector series (rigid: the centroid and
        the accumulated rotation vector; non-rigid: each moving Gaussian's
        position and rotation vector) at its fitted velocity, slowing to a stop
        where its last `window` values decelerate (trajectory.braking_polynomial)."""
        if not len(self.moving):
            return self.frozen_trajectory(n)
        return self.series_trajectory(braking_polynomial(self.series, window, n))

    def series_trajectory(self, future_series: np.ndarray) -> np.ndarray:
        """The trajectory of forecast series (same rows as self.series)."""
        n = future_series.shape[1]
        if self.rigid:
            r_last = self.series[3:, -1]
            g = integrate_rotvec(self.rotations[-1], r_last, future_series[3:].T)  # (n, 4): from the last frame
            return np.concatenate([future_series[:3].T, g], axis=-1)
        f = future_series.reshape(len(self.moving), 6, n).transpose(0, 2, 1)
        rv_last = self.series.reshape(len(self.moving), 6, -1)[:, 3:, -1]
        rot = integrate_rotvec(self.last[self.moving, 3:], rv_last, f[..., 3:])
        return np.concatenate([f[..., :3], rot], axis=-1)

    def start(self) -> np.ndarray:
        """The trajectory's pose at the last observed frame (its step 0)."""
        return self.frozen_trajectory(1)[..., 0, :]

    def slowed(self, trajectory: np.ndarray, half_life: float) -> np.ndarray:
        """The trajectory (this group's form, n steps) with its speed halving
        every `half_life` steps: read at damped_steps from start()."""
        n = trajectory.shape[-2]
        return time_warped(trajectory, self.start(), damped_steps(n, 0.5 ** (1.0 / half_life)))

    def members(self, trajectory: np.ndarray) -> np.ndarray:
        """Member poses (G, n, 7) of a trajectory (damped, if `damping`); still
        members keep their last pose."""
        n = trajectory.shape[-2]
        out = np.repeat(self.last[:, None, :], n, axis=1)
        if not len(self.moving):
            return out
        if self.damping > 0:
            trajectory = self.slowed(trajectory, self.damping * self.obs.shape[1])
        if self.rigid:
            members = self.last[self.moving]
            rel = members[:, :3] - self.centroids[-1]
            rotations = trajectory[None, :, 3:]
            out[self.moving, :, :3] = quat.rotate(rotations, rel[:, None, :]) + trajectory[None, :, :3]
            out[self.moving, :, 3:] = quat.mul(rotations, members[:, None, 3:])
        else:
            out[self.moving] = trajectory
        return out


def damped_steps(n: int, phi: float) -> np.ndarray:
    """(n,) the forecast step each of n steps is read at when the speed falls
    by phi per step: 1, 1 + phi, 1 + phi + phi^2, ... (Gardner and
    McKenzie's damped trend, for any trajectory)."""
    return np.cumsum(phi ** np.arange(n, dtype=np.float64))


def time_warped(trajectory: np.ndarray, start: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """A trajectory (..., n, 7) read at fractional steps (n,) in [0, n], step 0
    being `start` (..., 7): positions interpolated linearly, quaternions
    normalised-linearly on one hemisphere."""
    full = np.concatenate([start[..., None, :], trajectory], axis=-2)
    n = trajectory.shape[-2]
    i0 = np.clip(np.floor(steps).astype(np.int64), 0, n)
    i1 = np.minimum(i0 + 1, n)
    f = (steps - i0)[:, None]
    a, b = full[..., i0, :], full[..., i1, :]
    out = np.empty_like(trajectory)
    out[..., :3] = (1.0 - f) * a[..., :3] + f * b[..., :3]
    out[..., 3:] = quat.normalize((1.0 - f) * a[..., 3:] + f * quat.align_to(b[..., 3:], a[..., 3:]))
    return out
