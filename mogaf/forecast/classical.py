"""Training-free references: the frozen last pose and the constant body-frame twist."""

from __future__ import annotations

import numpy as np

from mogaf.forecast import quat
from mogaf.forecast.base import Forecaster


class Frozen(Forecaster):
    """The last observed pose, repeated."""

    NAME = "frozen"
    DEFAULTS: dict = {}
    MIN_FRAMES = 1

    def _fit(self, obs: np.ndarray) -> None:
        self._last = obs[:, -1].copy()

    def _rollout(self, n_steps: int) -> np.ndarray:
        return np.repeat(self._last[:, None, :], n_steps, axis=1)


def constant_twist_rollout(prev: np.ndarray, last: np.ndarray, n_steps: int) -> np.ndarray:
    """Repeat the body-frame increment D = T_prev^-1 T_last: T_{t+1} = T_t D.

    prev, last: (G, 7) poses. Float64 throughout; quaternions are renormalised
    after every composition so long rollouts stay on SO(3). With orientation
    co-rotating with the object this reproduces a uniform rigid rotation about
    any axis (and any screw motion) exactly.
    """
    q_prev = quat.normalize(prev[:, 3:])
    q_last = quat.normalize(last[:, 3:])
    q_prev = quat.align_to(q_prev, q_last)
    # D in the body frame of the previous pose.
    q_d = quat.normalize(quat.mul(quat.conj(q_prev), q_last))
    p_d = quat.rotate(quat.conj(q_prev), last[:, :3] - prev[:, :3])
    return twist_rollout(last[:, :3], q_last, q_d, p_d, n_steps)


def mean_twist(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The body-frame increment (q_d (G, 4), p_d (G, 3)) averaged over the
    k steps of poses (G, k + 1, 7): rotation vectors and translations are
    averaged, so a screw motion keeps its exact twist and noise in one step's
    fit weighs 1/k."""
    q = quat.make_continuous(quat.normalize(poses[..., 3:]), axis=-2)
    q_prev, q_next = q[:, :-1], q[:, 1:]
    inc = quat.normalize(quat.mul(quat.conj(q_prev), q_next))
    p_d = quat.rotate(quat.conj(q_prev), poses[:, 1:, :3] - poses[:, :-1, :3]).mean(axis=1)
    q_d = quat.normalize(quat.from_rotvec(quat.to_rotvec(inc).mean(axis=1)))
    return q_d, p_d


def twist_rollout(
    mu_last: np.ndarray, q_last: np.ndarray, q_d: np.ndarray, p_d: np.ndarray, n_steps: int
) -> np.ndarray:
    """T_{t+1} = T_t D from the last pose (mu_last (G, 3), q_last (G, 4)), D = (q_d, p_d) in the body frame."""
    out = np.empty((mu_last.shape[0], n_steps, 7))
    mu, q = mu_last.copy(), q_last.copy()
    for k in range(n_steps):
        mu = mu + quat.rotate(q, p_d)
        q = quat.normalize(quat.mul(q, q_d))
        out[:, k, :3] = mu
        out[:, k, 3:] = q
    return out


class ConstantVelocity(Forecaster):
    """Constant body-frame twist of each Gaussian's last two poses."""

    NAME = "constant_velocity"
    DEFAULTS: dict = {}
    MIN_FRAMES = 2

    def _fit(self, obs: np.ndarray) -> None:
        self._prev = obs[:, -2].copy()
        self._last = obs[:, -1].copy()

    def _rollout(self, n_steps: int) -> np.ndarray:
        return constant_twist_rollout(self._prev, self._last, n_steps)
