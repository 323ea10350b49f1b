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
    out = np.empty((last.shape[0], n_steps, 7))
    mu, q = last[:, :3].copy(), q_last.copy()
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
