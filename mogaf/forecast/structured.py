"""Structure-aware MoGaF: the default mode of the MoGaF forecaster
(`forecast.mogaf.mode: structured`; `mode: paper` is the paper's forecaster,
mogaf.forecast.transformer, unchanged).

It keeps the paper's network (LW encoder, instance normalisation, masked input
training, L_pred + lambda_acc L_acc) and changes what it is fed and how its
output is used. Why: a rigid group's 7-channel pose sequences are near copies
after instance normalisation, so the paper's fit learns little beyond the next
pose's normalised level, and Gaussians rolled out one by one drift apart.

  * Rigid groups (the grouping's hint, or a rigid-fit residual below
    `rigid_residual` of the group's radius) forecast one group trajectory
    (centroid + accumulated body-frame rotation vector, relative to the last
    observed frame) applied to every member, so they stay rigid. Non-rigid
    groups forecast each Gaussian.
  * Gaussians whose observed motion is below the trajectories' own noise
    level (`still_factor` x the median third difference; position and
    orientation in a non-rigid group, position in a rigid one) stay where
    they are; a rigid group's moving members follow its motion. A still part
    joined to a moving body is a grouping error, and moving it would carry a
    resting object away. (On a body spinning in place, members on the axis
    keep their orientation too.)
  * Channel-independent inputs (PatchTST / RevIN style): every scalar channel
    is its own sequence, anchored at its last value and divided by its spread,
    all through one shared network; a linear autoregression on one channel
    extrapolates a parabola or a sinusoid exactly, the 7-channel mix cannot.
  * The network predicts `horizon` steps at once as a residual over each
    channel's constant velocity, with a zero-initialised head, so the
    untrained model is that constant velocity. It trains on every sub-window
    (`context` values -> the next `horizon`) of every channel and rolls out
    `horizon` steps per forward pass.
  * Candidates, fitted per series like the network (`candidates`; the
    default: frozen, linear_trend and learned): frozen, constant_velocity (a
    rigid group's last twist: exact for a hinged lid), linear_trend (a
    least-squares line through the last `trend_window` values: a
    reconstruction's last frames are its least constrained, and a line
    through several values is less moved by them than a velocity from two)
    and constant_acceleration (a parabola over the last `context` values,
    which contacts bend off within the forecast).
  * A per-group backtest on observed frames only: each candidate is fitted
    on the first T - h frames and scored on the last h (h = backtest_frac * T,
    at most the forecast horizon). The learned candidate's score is combined
    (root sum of squares) with its refit drift (`drift_check`), since the
    refit on all T frames can learn a reconstruction's last-frame artefacts
    as motion. `combine: weighted` refits every candidate on all T frames and
    averages their forecasts, weighted by the inverse squared score (one
    backtest window is a noisy judge); a rigid group blends as one pose, and
    in a non-rigid group each moving Gaussian's weights come from the scores
    over its `backtest_neighbors` nearest moving Gaussians. `combine: select`
    refits and rolls out the best alone (`backtest_margin`: the share by
    which the learned forecaster must win). Scores, drift, weights and choice
    are recorded in the forecast's info. Without enough frames for a
    backtest the group keeps constant velocity. The decision depends on the
    forecast length (through h), so the first k steps of a longer forecast
    need not equal a k-step forecast.

Known limit: a rigid group whose members lie on one line has no observable
rotation about that line; Procrustes then picks one, which can turn the
members' orientations about it.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from mogaf.devices import resolve_device
from mogaf.errors import MogafError
from mogaf.forecast import quat
from mogaf.forecast.base import torch_determinism
from mogaf.forecast.classical import constant_twist_rollout
from mogaf.forecast.params import STRUCTURED_CANDIDATES, MogafSettings, StructuredSettings, load_mogaf
from mogaf.forecast.transformer_net import _build_model, mask_ratio, minibatches, optimiser_step, span_masks
from mogaf.progress import Progress

# forecast.mogaf.mode picks the forecaster; forecast.mogaf.structured holds the
# structured mode's own settings (the paper mode ignores them). Everything else
# (architecture, masking, lambda_acc, optimiser, runtime) is the paper mode's.
# None of these is in the paper: ours (docs/forecasting.md).
MODES = ("structured", "paper")


@dataclass(frozen=True)
class StructuredRun:
    """What the structured mode runs with: the network, masking and optimiser
    settings of forecast.mogaf (`net`) and forecast.mogaf.structured (`own`,
    whose weight_decay replaces the paper mode's)."""

    net: MogafSettings
    own: StructuredSettings


def structured_settings(p: Mapping[str, Any] | MogafSettings) -> StructuredRun:
    """forecast.mogaf and its `structured` part, checked (params.load_mogaf)."""
    return StructuredRun(*load_mogaf(p))


CANDIDATES = STRUCTURED_CANDIDATES  # tie order: the simpler wins


# ---------------------------------------------------------------- geometry
def accumulated_rotvec(q: np.ndarray) -> np.ndarray:
    """(..., T, 4) unit quaternions -> (..., T, 3): the sum of the body-frame
    rotation vectors of the steps so far (0 at the first frame). Unlike the
    rotation vector of the pose itself it never wraps at pi, so a spin of many
    turns is a straight line."""
    q = quat.make_continuous(q, axis=-2)
    steps = quat.to_rotvec(quat.mul(quat.conj(q[..., :-1, :]), q[..., 1:, :]))
    out = np.zeros(q.shape[:-1] + (3,))
    out[..., 1:, :] = np.cumsum(steps, axis=-2)
    return out


def integrate_rotvec(q_last: np.ndarray, r_last: np.ndarray, r_future: np.ndarray) -> np.ndarray:
    """Quaternions (..., n, 4) continuing q_last (..., 4) along the accumulated
    rotation vectors r_future (..., n, 3) that follow r_last (..., 3)."""
    steps = np.diff(np.concatenate([r_last[..., None, :], r_future], axis=-2), axis=-2)
    out = np.empty(r_future.shape[:-1] + (4,))
    q = quat.normalize(q_last)
    for k in range(steps.shape[-2]):
        q = quat.normalize(quat.mul(q, quat.from_rotvec(steps[..., k, :])))
        out[..., k, :] = q
    return out


def rigid_decomposition(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Best rigid motion of a group (G, T, 3) from its last frame to every frame.

    Returns centroids (T, 3), rotations (T, 4) wxyz with the identity at the
    last frame, and the relative residual: the largest per-frame RMS distance
    of the members from the rigid fit, over the group's RMS radius."""
    from mogaf.rigid import procrustes_numpy  # local: mogaf.rigid imports torch at module level

    pos = np.asarray(positions, dtype=np.float64)
    ref = pos[:, -1]
    centroids = pos.mean(axis=0)
    src = np.repeat((ref - centroids[-1])[None], pos.shape[1], axis=0)
    dst = np.moveaxis(pos, 1, 0) - centroids[:, None, :]
    R, _ = procrustes_numpy(src, dst)
    fitted = np.einsum("tij,tgj->tgi", R, src)
    residual = np.sqrt(np.mean(np.sum((fitted - dst) ** 2, axis=-1), axis=1))
    radius = float(np.sqrt(np.mean(np.sum(src[0] ** 2, axis=-1))))
    rel = float(residual.max() / radius) if radius > 0 else 0.0
    return centroids, quat.make_continuous(_matrix_to_quat(R), axis=0), rel


def _matrix_to_quat(R: np.ndarray) -> np.ndarray:
    import torch

    from mogaf.representation import matrix_to_quat  # local: mogaf.representation imports torch at module level

    return matrix_to_quat(torch.from_numpy(np.ascontiguousarray(R, dtype=np.float64))).numpy()


def _noise_level(series: np.ndarray) -> float:
    """Jitter of (G, T, 3) trajectories: the median over the group of each
    one's median third difference. Motion of constant acceleration has none,
    white noise of deviation s about 4.5 s (a norm of 3 components)."""
    return float(np.median(np.median(np.linalg.norm(np.diff(series, n=3, axis=1), axis=-1), axis=1)))


def still_gaussians(positions: np.ndarray, factor: float, quats: np.ndarray | None = None) -> np.ndarray:
    """(G,) True where a Gaussian's observed motion is below the noise level:
    it never moves further from its last position (and, with `quats`, never
    turns further from its last orientation) than factor x the group's jitter."""
    pos = np.asarray(positions, dtype=np.float64)
    if pos.shape[1] < 4:
        return np.zeros(pos.shape[0], bool)
    still = np.linalg.norm(pos - pos[:, -1:], axis=-1).max(axis=1) <= factor * _noise_level(pos)
    if quats is not None:
        rv = accumulated_rotvec(np.asarray(quats, dtype=np.float64))
        still &= np.linalg.norm(rv - rv[:, -1:], axis=-1).max(axis=1) <= factor * _noise_level(rv)
    return still


def rigid_group_still(positions: np.ndarray, factor: float) -> np.ndarray:
    """(G,) the still members of a rigid group: still_gaussians on positions
    (the reconstruction turns a joined resting part with the body), and none
    unless at least 3 members move, so a moving body remains: a fast turn's own
    third differences (the jitter estimate) can exceed every member's reach."""
    still = still_gaussians(positions, factor)
    if (~still).sum() < 3:
        still[:] = False
    return still


def local_polynomial(series: np.ndarray, window: int, degree: int, n_steps: int) -> np.ndarray:
    """(S, n_steps) values after the end of `series` (S, T) on each row's
    least-squares polynomial of `degree` (1: a line, 2: a parabola) through
    its last `window` values (of lower degree when fewer values are there:
    a line through two, the last value repeated with one). The fit, not the
    last value, starts the forecast: a fit through several values is less
    moved by the error of the last frame than a velocity taken from two."""
    values = np.asarray(series, dtype=np.float64)
    W = min(int(window), values.shape[1])
    degree = min(int(degree), W - 1)
    # time in units of the window, last value at 0: a well-conditioned design
    t = np.arange(-W + 1, 1, dtype=np.float64) / max(W - 1, 1)
    design = np.vander(t, degree + 1, increasing=True)  # (W, degree + 1)
    coef, *_ = np.linalg.lstsq(design, values[:, -W:].T, rcond=None)  # (degree + 1, S)
    future = np.arange(1, n_steps + 1, dtype=np.float64) / max(W - 1, 1)
    return (np.vander(future, degree + 1, increasing=True) @ coef).T


# ---------------------------------------------------------------- the learned part
def window_sizes(length: int, context: int, horizon: int) -> tuple[int, int] | None:
    """(context, horizon) that leave at least one training window in `length`
    values, or None when the series is too short for the learned forecaster."""
    h = max(1, min(horizon, (length - 1) // 3))
    c = min(context, length - h)
    return (c, h) if c >= 2 else None


class ChannelForecaster:
    """One shared network over independent scalar series (S, T): context ->
    next `horizon` values, a residual over each series' constant velocity."""

    def __init__(self, run: StructuredRun, seed: int, device: Any = "cpu") -> None:
        self.run = run
        self.seed = int(seed)
        # the torch device the network trains and runs on (a name is resolved: "auto" too)
        self.device = resolve_device(device, "forecast.mogaf") if isinstance(device, str) else device

    @staticmethod
    def normalise(ctx: np.ndarray, floor: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Anchor at the last value, divide by the spread (floored: a still
        channel is not blown up to unit scale)."""
        anchor = ctx[:, -1:]
        scale = np.sqrt(ctx.var(axis=1, keepdims=True) + floor[:, None] ** 2)
        return (ctx - anchor) / scale, anchor, scale

    def fit(self, series: np.ndarray, floor: np.ndarray) -> ChannelForecaster:
        import torch

        net, own = self.run.net, self.run.own
        S, T = series.shape
        sizes = window_sizes(T, int(own.context), int(own.horizon))
        if sizes is None:
            raise MogafError(f"forecast.mogaf: {T} observed frames are too few for the learned forecaster")
        self.context, self.horizon = L, H = sizes
        n_win = T - L - H + 1
        rng = np.random.default_rng([self.seed, 7])
        total = S * n_win
        # (channel, window) pairs drawn by flat index: a big group never builds all of them
        flat = (
            np.sort(rng.choice(total, int(own.max_train_windows), replace=False))
            if total > own.max_train_windows
            else np.arange(total)
        )
        pairs = np.stack(np.divmod(flat, n_win), axis=-1)
        idx = pairs[:, 1:2] + np.arange(L + H)[None, :]
        win = series[pairs[:, :1], idx]
        xn, anchor, scale = self.normalise(win[:, :L], floor[pairs[:, 0]])
        yn = (win[:, L:] - anchor) / scale
        steps_ahead = np.arange(1, H + 1, dtype=np.float64)

        dev = self.device
        with torch_determinism(self.seed, net.num_threads or None, dev):
            # the sampling generator stays on the CPU: the same draws on every device
            gen = torch.Generator().manual_seed(self.seed)
            # built on the CPU: the same initial weights on every device
            model = _build_model(L, net, in_dim=1, out_dim=H, zero_head=True).to(dev)
            X = torch.from_numpy(xn).float()[..., None].to(dev)
            Y = torch.from_numpy(yn).float().to(dev)
            K = torch.from_numpy(steps_ahead).float().to(dev)
            n = X.shape[0]
            opt = torch.optim.Adam(model.parameters(), lr=net.lr, weight_decay=own.weight_decay)
            sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=net.iterations, eta_min=net.lr_min)
            bs = min(int(net.batch_size), n)
            model.train()
            loss_val = float("nan")
            bar = Progress("forecast.mogaf fit", net.iterations)
            for it, b in minibatches(n, bs, net.iterations, gen):
                b = b.to(dev)
                x = X[b]
                mask = None
                span = int(round(mask_ratio(net, it) * (L - 2)))  # the last two values carry the prior
                if span > 0:
                    mask = span_masks(bs, L, span, L - 2, gen, dev)
                velocity = x[:, -1, 0] - x[:, -2, 0]
                pred = K[None, :] * velocity[:, None] + model(x, mask)
                l_pred = ((pred - Y[b]) ** 2).mean()
                seq = torch.cat([x[:, -2:, 0], pred], dim=1)
                l_acc = ((seq[:, 2:] - 2.0 * seq[:, 1:-1] + seq[:, :-2]) ** 2).mean()
                loss = l_pred + net.lambda_acc * l_acc
                optimiser_step(loss, model, opt, sched, net.grad_clip, it)
                loss_val = loss.item()
                bar.update(it + 1, loss=loss_val)
            bar.close()
            model.eval()
        self.model = model
        self.final_loss = loss_val
        self.num_windows = n
        return self

    def rollout(self, series: np.ndarray, floor: np.ndarray, n_steps: int) -> np.ndarray:
        """(S, n_steps) values after the end of `series` (S, >= context)."""
        import torch

        L, H = self.context, self.horizon
        hist = np.array(series[:, -L:], dtype=np.float64)
        out = np.empty((hist.shape[0], n_steps))
        chunk = int(self.run.net.rollout_chunk)
        steps_ahead = np.arange(1, H + 1, dtype=np.float64)
        done = 0
        with torch_determinism(self.seed, self.run.net.num_threads or None, self.device), torch.no_grad():
            while done < n_steps:
                xn, anchor, scale = self.normalise(hist[:, -L:], floor)
                res = np.empty((hist.shape[0], H))
                for s in range(0, hist.shape[0], chunk):
                    x = torch.from_numpy(xn[s : s + chunk]).float()[..., None].to(self.device)
                    res[s : s + chunk] = self.model(x).cpu().double().numpy()
                pred = steps_ahead[None, :] * (xn[:, -1:] - xn[:, -2:-1]) + res
                values = pred * scale + anchor
                take = min(H, n_steps - done)
                out[:, done : done + take] = values[:, :take]
                hist = np.concatenate([hist, values[:, :take]], axis=1)[:, -L:]
                done += take
        return out


# ---------------------------------------------------------------- group forecasts
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
    ) -> None:
        """`decomposition`: rigid_decomposition(obs[..., :3]) when already computed."""
        self.obs = obs
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

    def members(self, trajectory: np.ndarray) -> np.ndarray:
        """Member poses (G, n, 7) of a trajectory; still members keep their last pose."""
        n = trajectory.shape[-2]
        out = np.repeat(self.last[:, None, :], n, axis=1)
        if not len(self.moving):
            return out
        if self.rigid:
            members = self.last[self.moving]
            rel = members[:, :3] - self.centroids[-1]
            rotations = trajectory[None, :, 3:]
            out[self.moving, :, :3] = quat.rotate(rotations, rel[:, None, :]) + trajectory[None, :, :3]
            out[self.moving, :, 3:] = quat.mul(rotations, members[:, None, 3:])
        else:
            out[self.moving] = trajectory
        return out


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


# Least-squares polynomial candidates: (degree, the setting naming their window).
POLYNOMIAL_CANDIDATES = {"linear_trend": (1, "trend_window"), "constant_acceleration": (2, "context")}


class FittedCandidate:
    """A candidate fitted on a GroupMotion; rollout(n) gives member poses (G, n, 7).
    `model`: for learned, a network already fitted (on other frames) to use
    instead of fitting one on `motion`."""

    def __init__(
        self,
        name: str,
        motion: GroupMotion,
        run: StructuredRun,
        seed: int,
        device: Any = "cpu",
        model: ChannelForecaster | None = None,
    ) -> None:
        self.name, self.motion = name, motion
        self.polynomial = (
            (POLYNOMIAL_CANDIDATES[name][0], int(getattr(run.own, POLYNOMIAL_CANDIDATES[name][1])))
            if name in POLYNOMIAL_CANDIDATES
            else None
        )
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
            return m.polynomial_trajectory(n, window, degree)
        if self.name == "constant_velocity" or self.model is None:
            return m.constant_velocity_trajectory(n)
        return m.series_trajectory(self.model.rollout(m.series, m.floor, n))

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


def _distances(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(G, n) each member's distance at each step of (G, n, 7) poses."""
    return np.linalg.norm(pred[..., :3] - truth[..., :3], axis=-1)


def _score(pred: np.ndarray, truth: np.ndarray) -> float:
    return float(_distances(pred, truth).mean())


def fit_structured(
    obs: np.ndarray,
    p: Mapping[str, Any] | MogafSettings,
    seed: int,
    rigid_hint: bool | None,
    n_steps: int,
    device: Any = "cpu",
) -> tuple[FittedCandidate | WeightedCandidates, dict[str, Any]]:
    """The structured mode's fit of one group (G, T, 7) for a forecast of
    n_steps: the chosen candidate (combine: weighted, every candidate and its
    backtest weight), fitted on every observed frame, and what was decided
    (info; `choice` is the heaviest candidate under weighting). `p`: the MoGaF
    settings (forecast.mogaf, a mapping or MogafSettings); `device`: the torch
    device (or its name) of the learned candidate's network."""
    run = structured_settings(p)
    own = run.own
    G, T, _ = obs.shape
    # Fewer than 3 members fix no rotation: such a group is forecast per Gaussian.
    decomposition = rigid_decomposition(obs[..., :3]) if G >= 3 else None
    rel = decomposition[2] if decomposition is not None else None
    rigid = rel is not None and (bool(rigid_hint) if rigid_hint is not None else rel <= own.rigid_residual)
    info: dict[str, Any] = {
        "mode": "structured",
        "rigid": rigid,
        "rigid_residual_rel": rel,
        "rigid_source": "groups" if rigid_hint is not None and rel is not None else "residual",
    }
    context, horizon = int(own.context), int(own.horizon)
    h = max(1, min(int(n_steps), int(round(own.backtest_frac * T))))
    backtest_sizes = window_sizes(T - h, context, horizon)
    weights: dict[str, float] | None = None  # combine: weighted, once backtested
    backtest_steps = 0  # the backtest's network fit, counted in the group's optimiser steps
    candidates = [c for c in CANDIDATES if c in own.candidates]  # in tie order
    if not own.gate:
        choice = "learned" if window_sizes(T, context, horizon) else "constant_velocity"
    else:
        # Too few frames to backtest: nothing shows the learned forecaster is
        # better, so the group keeps its constant velocity.
        choice = "constant_velocity"
    motion = GroupMotion(obs, rigid, own.still_factor, decomposition)
    refit_learned: FittedCandidate | None = None  # the drift check's refit, kept for the forecast
    local = False  # the backtest weighs each moving member of a non-rigid group on its own
    member_weights: dict[str, np.ndarray] = {}
    if own.gate and backtest_sizes is not None:
        # Backtest on observed frames only: fit on the first T - h, score on the last h.
        # On short observations the backtested network reads a shorter context
        # (window_sizes) than the one refitted on all T frames, which keeps its own.
        past = GroupMotion(obs[:, : T - h], rigid, own.still_factor)
        scores = {}
        backtested = {}
        # combine: weighted, non-rigid: every moving member scored over its nearest
        # moving members (still ones are forecast still by every candidate); with
        # as many neighbours as moving members, the group's own weighting, exactly
        moving = motion.moving
        local = own.combine == "weighted" and not rigid and 0 < own.backtest_neighbors < len(moving)
        neighbours = nearest_members(obs[moving, -1, :3], int(own.backtest_neighbors)) if local else None
        member_scores: dict[str, np.ndarray] = {}
        for name in candidates:
            backtested[name] = FittedCandidate(name, past, run, seed, device)
            distances = _distances(backtested[name].rollout(h), obs[:, T - h :])
            scores[name] = float(distances.mean())
            if local:
                member_scores[name] = neighbour_mean(distances[moving].mean(axis=1), neighbours)
            info[f"backtest_epe_{name}"] = scores[name]
            backtest_steps += backtested[name].info.get("iterations", 0)
        learned_net = backtested["learned"].model if "learned" in backtested else None
        if own.drift_check and learned_net is not None and motion.series.shape[0] and np.isfinite(scores["learned"]):
            # The backtest judged a network that never saw the last h frames; the one
            # deployed is refitted on them. How far the two forecasts part is error
            # the backtest could not see (a reconstruction's last frames are its least
            # accurate, and a network can learn their artefacts as motion).
            refit_learned = FittedCandidate("learned", motion, run, seed, device)
            judged = FittedCandidate("learned", motion, run, seed, device, model=learned_net)
            distances = _distances(refit_learned.rollout(h), judged.rollout(h))
            drift = float(distances.mean())
            scores["learned"] = float(np.hypot(scores["learned"], drift))
            if local:
                member_drift = neighbour_mean(distances[moving].mean(axis=1), neighbours)
                member_scores["learned"] = np.hypot(member_scores["learned"], member_drift)
            info["learned_refit_drift"] = drift
        for name in member_scores:  # as in the group's weighting: no weight for a non-finite backtest
            if not np.isfinite(scores[name]):
                member_scores[name][:] = np.nan
        simple = min(
            (c for c in candidates if c != "learned"), key=lambda c: (scores[c], CANDIDATES.index(c)), default=None
        )
        learned_wins = "learned" in scores and (
            simple is None or scores["learned"] < (1.0 - own.backtest_margin) * scores[simple]
        )
        choice = "learned" if learned_wins else simple
        info["backtest_frames"] = h
        if own.combine == "weighted":
            if local:
                # each moving member's own weighting; the group's figures are their means
                member_weights = backtest_weights(member_scores)
                weights = {c: float(w.mean()) for c, w in member_weights.items()}
                info["backtest_neighbors"] = int(own.backtest_neighbors)
            else:
                weights = backtest_weights(scores)
            info.update({f"backtest_weight_{c}": w for c, w in weights.items()})
            choice = max(candidates, key=lambda c: weights[c])
    info["still_fraction"] = float(motion.still.mean())
    info["choice"] = choice

    def fitted_on_all(name: str) -> FittedCandidate:
        if name == "learned" and refit_learned is not None:
            return refit_learned
        return FittedCandidate(name, motion, run, seed, device)

    # every network fitted counts once: the backtest's, the drift check's refit (kept or not), any other
    steps = backtest_steps + (refit_learned.info.get("iterations", 0) if refit_learned is not None else 0)
    if weights is not None and max(weights.values()) < 1.0:
        fitted_all = [fitted_on_all(c) for c in candidates if weights[c] > 0.0]
        for c in fitted_all:
            info.update(c.info)
        info["iterations"] = steps + sum(c.info.get("iterations", 0) for c in fitted_all if c is not refit_learned)
        return WeightedCandidates(fitted_all, member_weights if local else weights), info
    fitted = fitted_on_all(choice)
    info.update(fitted.info)
    info["iterations"] = steps + (0 if fitted is refit_learned else fitted.info.get("iterations", 0))
    return fitted, info
