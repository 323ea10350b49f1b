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
    observed frame) applied to every member, so they stay rigid. A non-rigid
    group is cut into rigid parts (`nonrigid_motion: rigid_parts`, below),
    or forecast Gaussian by Gaussian (`per_gaussian`, and where its parts
    leave over `parts_unexplained` of its motion unexplained).
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
    through several values is less moved by them than a velocity from two),
    braking (the velocity of a parabola over the last `context` values,
    slowing to a stop where that parabola decelerates) and
    constant_acceleration (that parabola itself, which contacts bend off
    within the forecast).
  * A per-group backtest on observed frames only: each candidate is fitted
    on the first T - h frames and scored on the last h (h = backtest_frac * T,
    at most the forecast horizon). The learned candidate's score is combined
    (root sum of squares) with its refit drift (`drift_check`), since the
    refit on all T frames can learn a reconstruction's last-frame artefacts
    as motion. `combine: weighted` refits every candidate on all T frames and
    averages their forecasts, weighted by the inverse squared score (one
    backtest window is a noisy judge); a rigid group blends as one pose, and
    in a non-rigid group each moving Gaussian's weights come from the scores
    over its `backtest_neighbors` nearest moving Gaussians; `backtest_origins`
    > 1 also scores from later origins (about h/2, h/4, ... frames held
    back) and averages each candidate's weights over them. `combine: select`
    refits and rolls out the best alone (`backtest_margin`: the share by
    which the learned forecaster must win). Scores, drift, weights and choice
    are recorded in the forecast's info. Without enough frames for a
    backtest the group keeps constant velocity. The decision depends on the
    forecast length (through h), so the first k steps of a longer forecast
    need not equal a k-step forecast.

`coherent_neighbors` > 0 (off by default; variant coherent_forecast): in a
non-rigid group each moving Gaussian's forecast motion is replaced by the
local affine fit of its nearest moving Gaussians' motions
(candidates.neighbour_smoothed_poses), so noise extrapolated Gaussian by
Gaussian does not tear a surface apart.

`nonrigid_motion: rigid_body` (off by default; variant nonrigid_rigid_body): a
group that is not rigid is forecast as a rigid one is, its rigid-fit motion
carried to its moving members, whose shape stays as last observed.
`nonrigid_motion: rigid_parts` (the default; variant nonrigid_per_gaussian is
the other way): a group that is not rigid is cut into at most `rigid_parts`
parts that each move as one rigid body (trajectory.rigid_parts), and each
part is forecast as a rigid group, with its own backtest; the learned
candidate's networks are fitted once over all parts' series (SharedNetworks),
as a non-rigid group's one network is over its Gaussians'. A hinged lid and
the still body it is joined to, or the patches of a cloth, each keep their
shape, where each Gaussian's own extrapolated noise tears a surface apart.

Known limit: a rigid group whose members lie on one line has no observable
rotation about that line; Procrustes then picks one, which can turn the
members' orientations about it.

The forecaster's fit (StructuredMoGaF.fit, which needs the horizon) makes
that decision in three steps: backtest, weighting, refit; its rollout only
rolls out what the refit chose. Modules: trajectory (rotation and trajectory
helpers), group_motion (GroupMotion), channel_net (the learned candidate's
network), candidates (the candidates, their weights and blend).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mogaf.forecast.base import Forecaster
from mogaf.forecast.candidates import (
    FittedCandidate,
    WeightedCandidates,
    backtest_weights,
    member_distances,
    nearest_members,
    neighbour_mean,
    neighbour_smoothed_poses,
)
from mogaf.forecast.channel_net import ChannelForecaster, NetworkMean, window_sizes
from mogaf.forecast.group_motion import GroupMotion
from mogaf.forecast.mogaf_settings import MogafRun, load_run
from mogaf.forecast.params import MOGAF_DEFAULTS, STRUCTURED_CANDIDATES, StructuredSettings
from mogaf.forecast.trajectory import rigid_decomposition, rigid_parts, unexplained_motion


def group_motion(obs: np.ndarray, own: StructuredSettings, rigid_hint: bool | None) -> tuple[GroupMotion, dict]:
    """The group (G, T, 7) as one rigid body or Gaussian by Gaussian (the
    grouping's flag `rigid_hint`, else the rigid fit's residual), and what was
    decided (info)."""
    # Fewer than 3 members fix no rotation: such a group is forecast per Gaussian.
    decomposition = rigid_decomposition(obs[..., :3]) if obs.shape[0] >= 3 else None
    rel = decomposition[2] if decomposition is not None else None
    rigid = rel is not None and (bool(rigid_hint) if rigid_hint is not None else rel <= own.rigid_residual)
    info: dict[str, Any] = {
        "mode": "structured",
        "rigid": rigid,
        "rigid_residual_rel": rel,
        "rigid_source": "groups" if rigid_hint is not None and rel is not None else "residual",
    }
    as_body = rigid or (decomposition is not None and own.nonrigid_motion == "rigid_body")
    if as_body != rigid:
        info["forecast_as"] = "rigid_body"
    return GroupMotion(obs, as_body, own.still_factor, decomposition, damping=own.damping), info


def backtest_frames(length: int, own: StructuredSettings, horizon: int) -> int | None:
    """Observed frames the backtest holds back (backtest_frac of them, at most
    the forecast horizon); None when the frames before them are too few to fit
    the learned candidate (window_sizes), or the gate is off."""
    h = max(1, min(int(horizon), int(round(own.backtest_frac * length))))
    if not own.gate or window_sizes(length - h, int(own.context), int(own.horizon)) is None:
        return None
    return h


@dataclass
class Backtest:
    """The candidates fitted on the first T - h observed frames and scored on
    the last h. `member_scores`: each moving member's scores over its
    nearest moving members (`local`: combine weighted, non-rigid group)."""

    frames: int
    scores: dict[str, float]
    local: bool
    member_scores: dict[str, np.ndarray]
    refit_learned: FittedCandidate | None = None  # the drift check's refit on every frame, kept for the forecast
    iterations: int = 0  # optimiser steps of the networks fitted: the backtest's, the drift check's refit
    info: dict[str, Any] = field(default_factory=dict)
    drift: np.ndarray | None = None  # (G, h) the drift check's member distances per step
    later: list[OriginScores] = field(default_factory=list)  # backtest_origins > 1: the later origins


@dataclass
class OriginScores:
    """The candidates' scores from a later backtest origin: fitted on the
    first T - `frames` observed frames, scored on the last `frames`."""

    frames: int
    scores: dict[str, float]
    member_scores: dict[str, np.ndarray]


def origin_frames(h: int, origins: int) -> list[int]:
    """Observed frames held back at each backtest origin, earliest origin
    first: h, then about h/2, h/4, ... (at least 2, each fewer than the one
    before), at most `origins` of them."""
    out = [int(h)]
    while len(out) < origins:
        n = max(2, int(round(h / 2 ** len(out))))
        if n >= out[-1]:
            break
        out.append(n)
    return out


def backtest(
    obs: np.ndarray,
    motion: GroupMotion,
    candidates: list[str],
    run: MogafRun,
    seed: int,
    h: int,
    device: Any,
    horizon: int = 0,
    shared: SharedNetworks | None = None,
) -> Backtest:
    """Backtest on observed frames only: fit on the first T - h, score on the
    last h (and, backtest_origins > 1 under combine: weighted, from later
    origins too: _later_origin). On short observations the backtested network
    reads a shorter context (window_sizes) than the one refitted on all T
    frames, which keeps its own. `horizon`: the forecast's length, which the
    drift check's refit rolls out at once (kept for the forecast). `shared`:
    networks fitted over several groups' series, used instead of fitting the
    learned candidate's here (nonrigid_motion: rigid_parts)."""
    own, T = run.own, obs.shape[1]
    past = GroupMotion(obs[:, : T - h], motion.rigid, own.still_factor, damping=own.damping)
    # combine: weighted, non-rigid: every moving member scored over its nearest
    # moving members (still ones are forecast still by every candidate); with
    # as many neighbours as moving members, the group's own weighting, exactly
    moving = motion.moving
    local = own.combine == "weighted" and not motion.rigid and 0 < own.backtest_neighbors < len(moving)
    neighbours = nearest_members(obs[moving, -1, :3], int(own.backtest_neighbors)) if local else None
    bt = Backtest(h, {}, local, {})
    learned_net = None
    for name in candidates:
        model = shared.past if shared is not None and name == "learned" else None
        fitted = FittedCandidate(name, past, run, seed, device, model=model)
        _score(fitted, obs, h, name, bt.scores, bt.member_scores, moving, neighbours)
        bt.info[f"backtest_epe_{name}"] = bt.scores[name]
        bt.iterations += fitted.info.get("iterations", 0)
        if name == "learned":
            learned_net = fitted.model
    if own.drift_check and learned_net is not None and motion.series.shape[0] and np.isfinite(bt.scores["learned"]):
        _drift_check(bt, motion, learned_net, run, seed, device, neighbours, horizon, shared)
    _no_weight_where_non_finite(bt.scores, bt.member_scores)
    bt.info["backtest_frames"] = h
    origins = origin_frames(h, int(own.backtest_origins)) if own.combine == "weighted" else [h]
    for n in origins[1:]:
        bt.later.append(_later_origin(obs, motion, candidates, run, seed, device, n, learned_net, bt, neighbours))
    return bt


def _later_origin(
    obs: np.ndarray,
    motion: GroupMotion,
    candidates: list[str],
    run: MogafRun,
    seed: int,
    device: Any,
    n: int,
    learned_net: Any,
    bt: Backtest,
    neighbours: Any,
) -> OriginScores:
    """The candidates scored from a later origin, on the last n observed
    frames: the simple ones refitted on the first T - n, the learned one the
    backtest's network (fitted on the first T - h, no new fit) reading the
    first T - n as its context, its score combined with the drift check's
    drift over its first n steps. Scores and drift are recorded in bt.info
    (`..._last{n}`)."""
    own, T = run.own, obs.shape[1]
    past = GroupMotion(obs[:, : T - n], motion.rigid, own.still_factor, damping=own.damping)
    out = OriginScores(n, {}, {})
    for name in candidates:
        if name == "learned" and (learned_net is None or not past.series.shape[0]):
            fitted = FittedCandidate("constant_velocity", past, run, seed, device)  # the untrained network's forecast
        else:
            fitted = FittedCandidate(name, past, run, seed, device, model=learned_net if name == "learned" else None)
        _score(fitted, obs, n, name, out.scores, out.member_scores, motion.moving, neighbours)
        bt.info[f"backtest_epe_{name}_last{n}"] = out.scores[name]
    if bt.drift is not None:  # as the drift check does at the first origin
        drift = bt.drift[:, :n]
        bt.info[f"learned_refit_drift_last{n}"] = float(drift.mean())
        _with_drift(out.scores, out.member_scores, drift, motion, neighbours)
    _no_weight_where_non_finite(out.scores, out.member_scores)
    return out


def _score(
    fitted: FittedCandidate,
    obs: np.ndarray,
    n: int,
    name: str,
    scores: dict[str, float],
    member_scores: dict[str, np.ndarray],
    moving: np.ndarray,
    neighbours: Any,
) -> None:
    """A candidate's backtest score on the last n observed frames: its mean
    member distance, and (when scored per member, `neighbours` given) each
    moving member's mean over its nearest moving members."""
    distances = member_distances(fitted.rollout(n), obs[:, obs.shape[1] - n :])
    scores[name] = float(distances.mean())
    if neighbours is not None:
        member_scores[name] = neighbour_mean(distances[moving].mean(axis=1), neighbours)


def _with_drift(
    scores: dict[str, float],
    member_scores: dict[str, np.ndarray],
    drift: np.ndarray,
    motion: GroupMotion,
    neighbours: Any,
) -> None:
    """The learned candidate's scores combined (root sum of squares) with the
    members' drift (G, n): the group's with its mean, each moving member's
    (when scored per member) with its neighbours' mean."""
    scores["learned"] = float(np.hypot(scores["learned"], drift.mean()))
    if "learned" in member_scores:
        member_drift = neighbour_mean(drift[motion.moving].mean(axis=1), neighbours)
        member_scores["learned"] = np.hypot(member_scores["learned"], member_drift)


def _no_weight_where_non_finite(scores: dict[str, float], member_scores: dict[str, np.ndarray]) -> None:
    """As in the group's weighting: a candidate with a non-finite score gets no weight at any member."""
    for name in member_scores:
        if not np.isfinite(scores[name]):
            member_scores[name][:] = np.nan


def _drift_check(
    bt: Backtest,
    motion: GroupMotion,
    learned_net: Any,
    run: MogafRun,
    seed: int,
    device: Any,
    neighbours: Any,
    horizon: int = 0,
    shared: SharedNetworks | None = None,
) -> None:
    """The backtest judged a network that never saw the last h frames; the one
    deployed is refitted on them. How far the two forecasts part is error the
    backtest could not see (a reconstruction's last frames are its least
    accurate, and a network can learn their artefacts as motion): the learned
    candidate's scores are combined with it (root sum of squares)."""
    bt.refit_learned = refitted_learned(motion, run, seed, device, shared, rollout_steps=horizon)
    judged = FittedCandidate("learned", motion, run, seed, device, model=learned_net)
    bt.drift = member_distances(bt.refit_learned.rollout(bt.frames), judged.rollout(bt.frames))
    _with_drift(bt.scores, bt.member_scores, bt.drift, motion, neighbours)
    bt.info["learned_refit_drift"] = float(bt.drift.mean())
    bt.iterations += bt.refit_learned.info.get("iterations", 0)


@dataclass
class Weighting:
    """What the backtest decided: `choice` (under combine: weighted, the
    heaviest candidate) and, under combine: weighted, each candidate's weight
    (`weights`, the group's figure) and the weights the blend uses (`blend`:
    the same, or per moving member)."""

    choice: str
    weights: dict[str, float] | None = None
    blend: dict[str, Any] | None = None
    info: dict[str, Any] = field(default_factory=dict)


def weighting(bt: Backtest | None, candidates: list[str], own: StructuredSettings, length: int) -> Weighting:
    """The candidates' weights from the backtest (None: no backtest was run)."""
    if bt is None:
        if not own.gate:
            return Weighting(
                "learned" if window_sizes(length, int(own.context), int(own.horizon)) else "constant_velocity"
            )
        # Too few frames to backtest: nothing shows the learned forecaster is
        # better, so the group keeps its constant velocity.
        return Weighting("constant_velocity")
    scores = bt.scores
    simple = min(
        (c for c in candidates if c != "learned"),
        key=lambda c: (scores[c], STRUCTURED_CANDIDATES.index(c)),  # a tie goes to the simpler
        default=None,
    )
    learned_wins = "learned" in scores and (
        simple is None or scores["learned"] < (1.0 - own.backtest_margin) * scores[simple]
    )
    out = Weighting("learned" if learned_wins else simple)
    if own.combine != "weighted":
        return out
    if bt.local:
        # each moving member's own weighting; the group's figures are their means
        out.blend = _mean_weights([bt.member_scores] + [o.member_scores for o in bt.later])
        out.weights = {c: float(w.mean()) for c, w in out.blend.items()}
        out.info["backtest_neighbors"] = int(own.backtest_neighbors)
    else:
        out.weights = out.blend = _mean_weights([scores] + [o.scores for o in bt.later])
    if bt.later:
        out.info["backtest_origins"] = 1 + len(bt.later)
    out.info.update({f"backtest_weight_{c}": w for c, w in out.weights.items()})
    out.choice = max(candidates, key=lambda c: out.weights[c])
    return out


def _mean_weights(origin_scores: list[dict[str, Any]]) -> dict[str, Any]:
    """The candidates' backtest weights, each origin's own, averaged over the
    origins: every origin has one vote, however short its window (a short,
    late window's errors are small, and would carry little weight in a
    pooled score)."""
    weights = [backtest_weights(s) for s in origin_scores]
    mean = {c: sum(w[c] for w in weights) / len(weights) for c in weights[0]}
    return {c: (float(v) if np.ndim(v) == 0 else v) for c, v in mean.items()}


def refit(
    motion: GroupMotion,
    decision: Weighting,
    candidates: list[str],
    bt: Backtest | None,
    run: MogafRun,
    seed: int,
    device: Any,
    shared: SharedNetworks | None = None,
) -> tuple[FittedCandidate | WeightedCandidates, dict[str, Any]]:
    """The decision's candidates fitted on every observed frame (the drift
    check's refit reused): the chosen one, or, where several keep a weight,
    their blend; and their info (`iterations`: every network fitted counts
    once: the backtest's, the drift check's refit (kept or not), any other)."""
    kept = bt.refit_learned if bt is not None else None
    steps = bt.iterations if bt is not None else 0
    info: dict[str, Any] = {}

    def fitted_on_all(name: str) -> FittedCandidate:
        if name == "learned":
            return kept if kept is not None else refitted_learned(motion, run, seed, device, shared)
        return FittedCandidate(name, motion, run, seed, device)

    weights = decision.weights
    if weights is not None and max(weights.values()) < 1.0:
        fitted_all = [fitted_on_all(c) for c in candidates if weights[c] > 0.0]
        for c in fitted_all:
            info.update(c.info)
        info["iterations"] = steps + sum(c.info.get("iterations", 0) for c in fitted_all if c is not kept)
        return WeightedCandidates(fitted_all, decision.blend), info
    fitted = fitted_on_all(decision.choice)
    info.update(fitted.info)
    info["iterations"] = steps + (0 if fitted is kept else fitted.info.get("iterations", 0))
    return fitted, info


@dataclass
class SharedNetworks:
    """The learned candidate's networks of several rigid groups (a non-rigid
    group's parts, nonrigid_motion: rigid_parts), each fitted once over all
    their series, as a non-rigid group's one network is over its Gaussians':
    `past` on the first T - h observed frames (the backtest's), `full` on all
    T (the drift check's refit, the forecast's)."""

    past: ChannelForecaster
    full: tuple[ChannelForecaster, ...]  # refit_networks of them, from their own seeds
    iterations: int


# Seed offset between the networks of one refit (refit_networks): unrelated to
# the jobs' seeds, which are 1000 apart (mogaf.forecast.stage).
REFIT_SEED_STRIDE = 7919


def refitted_learned(
    motion: GroupMotion,
    run: MogafRun,
    seed: int,
    device: Any,
    shared: SharedNetworks | None = None,
    rollout_steps: int = 0,
) -> FittedCandidate:
    """The learned candidate refitted on every observed frame: its
    refit_networks networks (seeds seed, seed + REFIT_SEED_STRIDE, ...; the
    `shared` ones where given) roll out as their mean. Its info is the first
    fit's, with every fit's optimiser steps."""
    if shared is not None:
        model = _one(shared.full)
        return FittedCandidate("learned", motion, run, seed, device, model=model, rollout_steps=rollout_steps)
    n = int(run.own.refit_networks)
    fits = [
        FittedCandidate("learned", motion, run, seed + k * REFIT_SEED_STRIDE, device, rollout_steps=rollout_steps)
        for k in range(n)
    ]
    if n == 1 or fits[0].model is None:  # one network, or every Gaussian still: no network
        return fits[0]
    model = NetworkMean(tuple(f.model for f in fits))
    out = FittedCandidate("learned", motion, run, seed, device, model=model, rollout_steps=rollout_steps)
    out.info = {**fits[0].info, "iterations": sum(f.info["iterations"] for f in fits)}
    return out


def _one(nets: tuple[ChannelForecaster, ...]) -> ChannelForecaster | NetworkMean:
    return nets[0] if len(nets) == 1 else NetworkMean(nets)


def shared_networks(
    observed: list[np.ndarray], run: MogafRun, seed: int, device: Any, horizon: int
) -> SharedNetworks | None:
    """The networks the rigid groups `observed` (each (G_i, T, 7)) share, or
    None where none is fitted (no learned candidate, no backtest)."""
    own, T = run.own, observed[0].shape[1]
    h = backtest_frames(T, own, horizon)
    if "learned" not in own.candidates or h is None:
        return None

    def fitted(frames: int, net_seed: int) -> ChannelForecaster:
        motions = [GroupMotion(o[:, :frames], True, own.still_factor, damping=own.damping) for o in observed]
        series = np.concatenate([m.series for m in motions])
        return ChannelForecaster(run, net_seed, device).fit(series, np.concatenate([m.floor for m in motions]))

    n = int(own.refit_networks)
    full = tuple(fitted(T, seed + k * REFIT_SEED_STRIDE) for k in range(n))
    return SharedNetworks(fitted(T - h, seed), full, (1 + n) * int(run.net.iterations))


class StructuredMoGaF(Forecaster):
    """The structured MoGaF forecaster (forecast.mogaf, `mode: structured`).
    Its fit depends on the forecast's length (the backtest holds back at most
    the horizon): fit(observed, rigid, horizon) fits, rollout(horizon) rolls
    out the refit candidates."""

    NAME = "mogaf"
    DEFAULTS = MOGAF_DEFAULTS
    MIN_FRAMES = 3  # as the paper mode's (the method's input check is one)
    NEEDS_HORIZON = True
    shared: SharedNetworks | None = None  # a part's forecaster (rigid_parts): its group's networks

    @classmethod
    def load_settings(cls, params: Any) -> MogafRun:
        return load_run(cls.NAME, cls.DEFAULTS, params, {})

    def _fit(self, obs: np.ndarray) -> None:
        device = self.device  # resolved (and recorded) even where no network is fitted
        run = self.settings
        self.parts: list[tuple[np.ndarray, StructuredMoGaF]] | None = None  # nonrigid_motion: rigid_parts
        own, T = run.own, obs.shape[1]
        motion, info = group_motion(obs, own, self.rigid_hint)
        if not motion.rigid and own.nonrigid_motion == "rigid_parts" and obs.shape[0] >= 3:
            labels = rigid_parts(obs[..., :3], int(own.rigid_parts), self.seed)
            info["parts_unexplained"] = unexplained_motion(obs[..., :3], labels)
            if info["parts_unexplained"] <= own.parts_unexplained:
                self._fit_parts(obs, labels, info)
                return
        candidates = [c for c in STRUCTURED_CANDIDATES if c in own.candidates]  # in tie order
        h = backtest_frames(T, own, self.horizon)
        shared = self.shared
        bt = (
            backtest(obs, motion, candidates, run, self.seed, h, device, self.horizon, shared)
            if h is not None
            else None
        )
        decision = weighting(bt, candidates, own, T)
        if bt is not None:
            info.update(bt.info)
        info.update(decision.info)
        info["still_fraction"] = float(motion.still.mean())
        info["choice"] = decision.choice
        self.fitted, refit_info = refit(motion, decision, candidates, bt, run, self.seed, device, shared)
        self.motion = motion
        self.coherent = coherent_neighbours(motion, int(own.coherent_neighbors))
        if self.coherent is not None:
            info["coherent_neighbors"] = int(self.coherent.shape[1])
        self.info.update(info)
        self.info.update(refit_info)

    def _fit_parts(self, obs: np.ndarray, labels: np.ndarray, info: dict[str, Any]) -> None:
        """nonrigid_motion: rigid_parts: each part (`labels`, rigid_parts) fitted as a rigid group."""
        run = self.settings
        groups = [np.flatnonzero(labels == p) for p in range(int(labels.max()) + 1)]
        shared = shared_networks([obs[m] for m in groups], run, self.seed, self.device, self.horizon)
        self.parts = []
        for members in groups:
            part = StructuredMoGaF(run, self.seed, self.device_name)
            part.shared = shared
            self.parts.append((members, part.fit(obs[members], rigid=True, horizon=self.horizon)))
        infos = [part.info for _, part in self.parts]
        info["forecast_as"] = "rigid_parts"
        # space-separated, as a job's info keeps scalars (metrics.json)
        sizes = [int(len(members)) for members, _ in self.parts]
        info["parts"] = len(sizes)
        info["part_members"] = " ".join(map(str, sizes))
        info["part_choices"] = " ".join(str(i["choice"]) for i in infos)
        info["choice"] = "rigid_parts"
        info["still_fraction"] = float(sum(i["still_fraction"] * n for i, n in zip(infos, sizes)) / len(obs))
        info["iterations"] = int(sum(i.get("iterations", 0) for i in infos)) + (shared.iterations if shared else 0)
        self.info.update(info)

    def bodies(self) -> np.ndarray:
        """A rigid group (or one forecast as one body): every member on body 0;
        rigid parts: each its part; per Gaussian: -1."""
        if self.parts is not None:
            labels = np.full(self._obs.shape[0], -1, np.int64)
            for p, (members, _) in enumerate(self.parts):
                labels[members] = p
            return labels
        return np.full(self._obs.shape[0], 0 if self.motion.rigid else -1, np.int64)

    def _rollout(self, n_steps: int) -> np.ndarray:
        if self.parts is not None:
            poses = np.empty((self._obs.shape[0], n_steps, 7))
            for members, part in self.parts:
                poses[members] = part.rollout(n_steps)
            return poses
        poses = self.fitted.rollout(n_steps)
        if self.coherent is not None:
            moving = self.motion.moving
            poses[moving] = neighbour_smoothed_poses(poses[moving], self.motion.last[moving], self.coherent)
        return poses


def coherent_neighbours(motion: GroupMotion, k: int) -> np.ndarray | None:
    """(M, k) each moving member's k nearest moving members at the last
    observed frame (coherent_neighbors), or None where nothing is smoothed: a
    rigid group (already one motion), k < 2 or fewer than 2 moving members."""
    if motion.rigid or k < 2 or len(motion.moving) < 2:
        return None
    return nearest_members(motion.last[motion.moving, :3], k)
