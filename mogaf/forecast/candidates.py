"""The structured MoGaF forecaster's candidates (frozen, constant_velocity,
linear_trend, damped_trend, braking, constant_acceleration, learned), fitted on a
GroupMotion, and what the backtest weighs them with: member distances,
inverse-squared-error weights, nearest moving members and the blend of their
forecasts."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from mogaf.errors import MogafError
from mogaf.forecast import quat
from mogaf.forecast.channel_net import ChannelForecaster
from mogaf.forecast.group_motion import GroupMotion
from mogaf.forecast.mogaf_settings import MogafRun


def blend_trajectories(trajectories: list[np.ndarray], weights: np.ndarray) -> np.ndarray:
    """Weighted mean of pose trajectories (..., 7): positions linearly,
    rotations as the normalised weighted sum of quaternions on the heaviest
    one's hemisphere (the chordal mean; for a rigid group's pose it stays one
    rotation, so the blend is rigid). `weights`: (C,) for the C trajectories,
    or (C, M) for trajectories (M, n, 7), one weighting per row."""
    weights = np.asarray(weights, dtype=np.float64)
    if weights.ndim == 2 and trajectories[0].ndim != 3:
        raise ValueError("blend_trajectories: per-row weights (C, M) need trajectories of shape (M, n, 7)")
    if weights.ndim == 1:
        ref = trajectories[int(np.argmax(weights))][..., 3:]
    else:
        ref = np.stack(trajectories)[np.argmax(weights, axis=0), np.arange(weights.shape[1]), ..., 3:]
    out = np.zeros_like(trajectories[0])
    for traj, w in zip(trajectories, weights, strict=True):
        w = np.reshape(w, np.shape(w) + (1,) * (traj.ndim - np.ndim(w)))  # per row: (M, 1, 1)
        out[..., :3] += w * traj[..., :3]
        out[..., 3:] += w * quat.align_to(traj[..., 3:], ref)
    out[..., 3:] = quat.normalize(out[..., 3:])
    return out


def backtest_weights(scores: Mapping[str, Any]) -> dict[str, Any]:
    """Inverse-squared-error weights of the candidates' backtest scores (Bates
    & Granger's combination with independent errors). A candidate with an
    exact backtest (score 0, e.g. frozen on a group that stopped) takes all
    the weight (several exact ones share it); a non-finite score takes none,
    and with every score non-finite there is nothing to weigh: an error.
    Scores are floats (weights are floats) or arrays of one shape, each
    element weighed on its own (weights are arrays)."""
    names = list(scores)
    s = np.array([scores[c] for c in names], dtype=np.float64)  # (C, ...)
    finite = np.isfinite(s)
    if not finite.any(axis=0).all():
        raise MogafError("forecast.mogaf: every candidate's backtest score is non-finite")
    best = np.min(np.where(finite, s, np.inf), axis=0)
    exact = np.where(finite & (s <= 0.0), 1.0, 0.0)
    inverse = np.where(finite, (best / np.where(finite & (s > 0.0), s, 1.0)) ** 2, 0.0)
    w = np.where(best <= 0.0, exact, inverse)
    w /= w.sum(axis=0)
    return {c: (float(v) if s.ndim == 1 else v) for c, v in zip(names, w, strict=True)}


def nearest_members(positions: np.ndarray, k: int) -> np.ndarray:
    """(G, k) each member's k nearest members (itself included) at positions
    (G, 3); k at most G."""
    from scipy.spatial import cKDTree

    k = min(int(k), len(positions))
    return cKDTree(positions).query(positions, k=k)[1].reshape(len(positions), k)


def neighbour_mean(values: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """(G,) each member's mean of `values` (G,) over its neighbours (G, k) (nearest_members)."""
    return values[neighbours].mean(axis=1)


def local_linear_fit(values: np.ndarray, positions: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """(M, D) each member's value of the least-squares affine function of
    position fitted to `values` (M, D) over its neighbours (M, k) at
    `positions` (M, 3): a field that is affine over a neighbourhood (a
    shift, a small turn, a stretch) is kept, what varies faster (noise) is
    averaged out. The slopes carry a ridge of LOCAL_LINEAR_RIDGE x the
    neighbourhood's mean squared distance, so a flat or thin neighbourhood
    (a surface, a rod) has no slope across itself."""
    m, k = neighbours.shape
    out = np.empty((m, values.shape[1]))
    # members per pass: the gathered neighbour values (chunk, k, D) stay near 64 MB
    chunk = max(1, LOCAL_LINEAR_CHUNK // (k * max(1, values.shape[1])))
    for start in range(0, m, chunk):
        nb = neighbours[start : start + chunk]
        rel = positions[nb] - positions[start : start + chunk, None, :]  # (c, k, 3)
        design = np.concatenate([np.ones(rel.shape[:2] + (1,)), rel], axis=-1)  # (c, k, 4)
        normal = np.einsum("cki,ckj->cij", design, design)
        spread = np.einsum("cki,cki->c", rel, rel) / k
        ridge = np.maximum(LOCAL_LINEAR_RIDGE * spread, np.finfo(np.float64).tiny)
        normal[:, 1:, 1:] += ridge[:, None, None] * np.eye(3)
        rhs = np.einsum("cki,ckd->cid", design, values[nb])
        out[start : start + chunk] = np.linalg.solve(normal, rhs)[:, 0]
    return out


LOCAL_LINEAR_RIDGE = 1e-2  # ours: small beside a full neighbourhood's k x spread, large beside a flat one's thickness
LOCAL_LINEAR_CHUNK = 1 << 23  # float64 values gathered per pass


def neighbour_smoothed_poses(poses: np.ndarray, last: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """Forecast poses (M, n, 7) with each member's motion since its last
    observed pose `last` (M, 7), displacement and rotation, replaced by the
    local affine fit over its neighbours (M, k) (nearest_members at the last
    observed frame, itself included): local_linear_fit of the displacements
    and of the relative quaternions, each on the identity's side (w >= 0),
    renormalised (for the small turns of a few forecast steps, close to a
    fit of the turns themselves)."""
    poses = np.asarray(poses, np.float64)
    last = np.asarray(last, np.float64)
    m, n = poses.shape[:2]
    shift = (poses[..., :3] - last[:, None, :3]).reshape(m, n * 3)
    identity = np.array([1.0, 0.0, 0.0, 0.0])
    turn = quat.align_to(quat.mul(poses[..., 3:], quat.conj(last[:, None, 3:])), identity).reshape(m, n * 4)
    fitted = local_linear_fit(np.concatenate([shift, turn], axis=1), last[:, :3], neighbours)
    fitted_turn = fitted[:, n * 3 :].reshape(m, n, 4)
    norm = np.linalg.norm(fitted_turn, axis=-1, keepdims=True)
    # Opposite turns of the same size cancel: no fitted turn, so no turn.
    fitted_turn = np.where(norm > 1e-12, fitted_turn / np.where(norm > 1e-12, norm, 1.0), identity)
    out = np.empty_like(poses)
    out[..., :3] = last[:, None, :3] + fitted[:, : n * 3].reshape(m, n, 3)
    out[..., 3:] = quat.normalize(quat.mul(fitted_turn, last[:, None, 3:]))
    return out


# Least-squares polynomial candidates: (degree, the setting naming their window).
POLYNOMIAL_CANDIDATES = {
    "linear_trend": (1, "trend_window"),
    "damped_trend": (1, "trend_window"),
    "braking": (2, "context"),
    "constant_acceleration": (2, "context"),
}
# Candidates whose polynomial slows down: the setting naming its speed's half-life in steps.
DAMPED_CANDIDATES = {"damped_trend": "trend_half_life"}


class FittedCandidate:
    """A candidate fitted on a GroupMotion; rollout(n) gives member poses (G, n, 7).
    `model`: for learned, a network already fitted (on other frames) to use
    instead of fitting one on `motion`. `rollout_steps`: the learned network
    rolls out at least this many steps when first asked and keeps them, so a
    later rollout within them (the forecast after the drift check's shorter
    one) reuses them: each block of the network's steps reads only the blocks
    before it, so a prefix is the same values as a shorter rollout."""

    def __init__(
        self,
        name: str,
        motion: GroupMotion,
        run: MogafRun,
        seed: int,
        device: Any = "cpu",
        model: ChannelForecaster | None = None,
        rollout_steps: int = 0,
    ) -> None:
        self.name, self.motion = name, motion
        self.rollout_steps = int(rollout_steps)
        self._series_future: np.ndarray | None = None
        self.polynomial = (
            (POLYNOMIAL_CANDIDATES[name][0], int(getattr(run.own, POLYNOMIAL_CANDIDATES[name][1])))
            if name in POLYNOMIAL_CANDIDATES
            else None
        )
        self.half_life = float(getattr(run.own, DAMPED_CANDIDATES[name])) if name in DAMPED_CANDIDATES else None
        self.info: dict[str, Any] = {}
        self.model = model
        if name == "learned" and model is None and motion.series.shape[0]:  # (no series: every Gaussian still)
            self.model = ChannelForecaster(run, seed, device).fit(motion.series, motion.floor)
            self.info = {
                "iterations": int(run.net.iterations),
                "final_loss": self.model.final_loss,
                "context": self.model.context,
                "horizon": self.model.horizon,
                "train_windows": self.model.num_windows,
            }

    def trajectory(self, n: int) -> np.ndarray:
        """The candidate's trajectory (GroupMotion's form) over n steps."""
        m = self.motion
        if self.name == "frozen":
            return m.frozen_trajectory(n)
        if self.polynomial is not None:
            degree, window = self.polynomial
            if self.name == "braking":  # the parabola's velocity, slowing to a stop
                return m.braking_trajectory(n, window)
            fitted = m.polynomial_trajectory(n, window, degree)
            return fitted if self.half_life is None else m.slowed(fitted, self.half_life)
        if self.name == "constant_velocity" or self.model is None:
            return m.constant_velocity_trajectory(n)
        return m.series_trajectory(self.series_future(n))

    def series_future(self, n: int) -> np.ndarray:
        """The learned network's next n values of every series (S, n), from the kept rollout where it is long enough."""
        if self._series_future is None or self._series_future.shape[1] < n:
            m = self.motion
            self._series_future = self.model.rollout(m.series, m.floor, max(n, self.rollout_steps))
        return self._series_future[:, :n]

    def rollout(self, n: int) -> np.ndarray:
        if self.name == "frozen":  # exactly the last poses (carrying the identity would round them)
            return np.repeat(self.motion.last[:, None, :], n, axis=1)
        return self.motion.members(self.trajectory(n))


class WeightedCandidates:
    """The candidates' forecasts blended by their backtest weights (combine:
    weighted): a float per candidate, or (backtest_neighbors) an array over
    the moving members of a non-rigid group."""

    def __init__(self, candidates: list[FittedCandidate], weights: Mapping[str, Any]) -> None:
        self.candidates = candidates
        self.weights = np.array([weights[c.name] for c in candidates])
        self.motion = candidates[0].motion

    def rollout(self, n: int) -> np.ndarray:
        trajectories = [c.trajectory(n) for c in self.candidates]
        return self.motion.members(blend_trajectories(trajectories, self.weights))


def member_distances(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(G, n) each member's distance at each step of (G, n, 7) poses."""
    return np.linalg.norm(pred[..., :3] - truth[..., :3], axis=-1)
