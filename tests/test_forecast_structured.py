"""The structured (default) MoGaF mode: rigid groups stay rigid, still parts stay
still, the backtest gate, the helpers it is built on, and the paper mode kept
selectable."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mogaf.errors import MogafError
from mogaf.forecast import candidates, quat
from mogaf.forecast.candidates import (
    FittedCandidate,
    WeightedCandidates,
    backtest_weights,
    blend_trajectories,
    nearest_members,
    neighbour_mean,
    neighbour_smoothed_poses,
)
from mogaf.forecast.channel_net import NetworkMean, window_sizes
from mogaf.forecast.coherence import coherence, rigid_distance_change
from mogaf.forecast.group_motion import GroupMotion, damped_steps, time_warped
from mogaf.forecast.mogaf_settings import load_run
from mogaf.forecast.params import MOGAF_DEFAULTS, STRUCTURED_CANDIDATES, inert_settings
from mogaf.forecast.registry import fit_and_rollout, make_forecaster
from mogaf.forecast.structured import REFIT_SEED_STRIDE, StructuredMoGaF, origin_frames, refitted_learned
from mogaf.forecast.synthetic import add_noise, ballistic_sphere, rigid_box, rigid_motion, waving_sheet
from mogaf.forecast.trajectory import (
    accumulated_rotvec,
    braking_polynomial,
    braking_polynomial_reference,
    integrate_rotvec,
    local_polynomial,
    rigid_decomposition,
    rigid_group_still,
    rigid_parts,
    still_gaussians,
)

# about 45 s with two workers: collected early (tests/conftest.py)
pytestmark = pytest.mark.long(seconds=45)

# Small budgets: behaviour, not converged accuracy.
QUICK = {"iterations": 60, "batch_size": 32}
# Each moving Gaussian of a non-rigid group forecast on its own (the default cuts it into rigid parts).
PER_GAUSSIAN = {**QUICK, "structured": {"nonrigid_motion": "per_gaussian"}}
# The default candidates, named where a test depends on them.
DEFAULT_CANDIDATES = ["frozen", "linear_trend", "learned"]
# The previous default, where a test is about the two-frame velocity (on a thrown
# sphere the parabola of constant_acceleration would win every backtest).
WITH_VELOCITY = ["frozen", "constant_velocity", "learned"]


def _weights_of_the_scores(info: dict) -> dict[str, float]:
    """The default candidates' weights as backtest_weights gives them for the
    recorded scores, the learned one's combined with its refit drift."""
    scores = {c: info[f"backtest_epe_{c}"] for c in DEFAULT_CANDIDATES}
    scores["learned"] = float(np.hypot(scores["learned"], info["learned_refit_drift"]))
    return backtest_weights(scores)


def _fit_structured(obs: np.ndarray, params: dict, seed: int, rigid: bool | None, horizon: int):
    """The structured forecaster fitted for a forecast of `horizon` steps:
    (what it rolls out, a candidate or their blend; its info, times left out)."""
    fc = make_forecaster("mogaf", params, seed).fit(obs, rigid=rigid, horizon=horizon)
    assert isinstance(fc, StructuredMoGaF)
    return fc.fitted, {k: v for k, v in fc.info.items() if not k.endswith("_time_s")}


def _pairwise_change(poses: np.ndarray, last: np.ndarray) -> float:
    return rigid_distance_change(last[:, :3], poses[..., :3], np.random.default_rng(0))[0]


# ---------------------------------------------------------------- helpers
def test_rotvec_round_trip_near_zero_and_near_pi():
    rng = np.random.default_rng(0)
    axes = rng.normal(size=(6, 3))
    angles = np.array([0.0, 1e-9, 1e-4, 1.0, 3.0, np.pi - 1e-6])
    q = quat.from_axis_angle(axes, angles)
    r = quat.to_rotvec(q)
    np.testing.assert_allclose(np.linalg.norm(r, axis=-1), angles, atol=1e-9)
    back = quat.from_rotvec(r)
    assert np.all(quat.angle_between(back, q) < 1e-8)
    assert np.isfinite(quat.to_rotvec(np.array([1.0, 0.0, 0.0, 0.0]))).all()


def test_accumulated_rotvec_unwraps_many_turns():
    # 0.5 rad per step about z for 40 steps: 20 rad, more than three turns
    t = np.arange(40)
    q = quat.from_axis_angle(np.broadcast_to([0.0, 0.0, 1.0], (40, 3)), 0.5 * t)
    r = accumulated_rotvec(q)
    np.testing.assert_allclose(r[:, 2], 0.5 * t, atol=1e-9)
    cont = integrate_rotvec(q[-1], r[-1], r[-1] + 0.5 * np.arange(1, 4)[:, None] * np.array([0, 0, 1.0]))
    want = quat.from_axis_angle(np.broadcast_to([0.0, 0.0, 1.0], (3, 3)), 0.5 * np.arange(40, 43))
    assert np.all(quat.angle_between(cont, want) < 1e-9)


def test_rigid_decomposition_recovers_the_motion_and_flags_deformation():
    box = rigid_box(64, 20)
    c, q, rel = rigid_decomposition(box[..., :3])
    assert rel < 1e-9
    np.testing.assert_allclose(c, box[..., :3].mean(0), atol=1e-12)
    assert quat.angle_between(q[-1], np.array([1.0, 0, 0, 0])) < 1e-9
    sheet = waving_sheet(64, 20)
    assert rigid_decomposition(sheet[..., :3])[2] > 0.05


def test_still_gaussians_are_those_below_the_noise_level():
    rng = np.random.default_rng(1)
    moving = rigid_box(40, 24)[..., :3]
    still = np.repeat(rng.uniform(-1, 1, (40, 1, 3)), 24, axis=1) + rng.normal(0, 1e-3, (40, 24, 3))
    flags = still_gaussians(np.concatenate([moving, still]), 3.0)
    assert not flags[:40].any() and flags[40:].all()


def test_window_sizes_shrink_with_the_observation():
    assert window_sizes(36, 16, 8) == (16, 8)
    assert window_sizes(12, 16, 8) == (9, 3)
    assert window_sizes(3, 16, 8) == (2, 1)
    assert window_sizes(2, 16, 8) is None


# ---------------------------------------------------------------- structure
@pytest.mark.parametrize("rigid_hint", [None, True])
def test_rigid_group_forecast_stays_rigid(rigid_hint):
    obs = add_noise(rigid_box(128, 30), pos_sigma=0.002, rot_sigma=0.0)
    res = fit_and_rollout("mogaf", obs, 20, QUICK, seed=0, rigid=rigid_hint)
    assert res.info["rigid"] is True
    change = _pairwise_change(res.poses, obs[:, -1])
    assert change < 1e-9
    # every Gaussian's orientation turns by the group's rotation
    rel = quat.mul(res.poses[:, :, 3:], quat.conj(obs[:, -1:, 3:]))
    assert np.all(quat.angle_between(rel, rel[:1]) < 1e-7)
    # the paper's forecaster rolls each Gaussian out on its own: the box deforms
    paper = fit_and_rollout("mogaf_paper", obs, 20, QUICK, seed=0)
    assert _pairwise_change(paper.poses, obs[:, -1]) > 100 * max(change, 1e-9)


def _screw(g: int, t: int, omega: float) -> np.ndarray:
    """A rigid body turning by omega per frame about a tilted axis far from its
    centroid while sliding along it: a constant twist, so its future is known."""
    from mogaf.forecast.synthetic import rigid_motion

    rng = np.random.default_rng(9)
    pts = rng.uniform(-0.3, 0.3, (g, 3)) + np.array([1.5, 0.0, 0.0])
    q0 = quat.canonical_sign(quat.normalize(rng.normal(size=(g, 4))))
    k = np.arange(t, dtype=np.float64)
    axis = np.array([0.2, -0.3, 1.0])
    rot = quat.from_axis_angle(np.broadcast_to(axis, (t, 3)), omega * k)
    trans = k[:, None] * 0.02 * axis / np.linalg.norm(axis)
    return rigid_motion(pts, q0, np.zeros(3), rot, trans)


@pytest.mark.parametrize("omega", [0.05, 1.2])
def test_rigid_constant_twist_candidate_is_exact_on_a_screw_motion(omega):
    """The rigid path's constant velocity carries the group's twist: a screw
    about an axis off the centroid, fast or slow, is continued exactly, and
    every member's orientation turns with the body."""
    traj = _screw(24, 30, omega)
    obs, fut = traj[:, :20], traj[:, 20:]
    motion = GroupMotion(obs, True, 3.0)
    pred = motion.members(motion.constant_velocity_trajectory(10))
    np.testing.assert_allclose(pred[..., :3], fut[..., :3], atol=1e-9)
    assert np.all(quat.angle_between(pred[..., 3:], fut[..., 3:]) < 1e-9)


def test_rigid_poses_from_the_true_future_series_are_the_truth():
    """GroupMotion.series_trajectory is the inverse of the decomposition: fed the true
    future centroids and accumulated rotation vectors, it gives the true poses."""
    traj = _screw(24, 30, 0.3)
    whole = GroupMotion(traj, True, 3.0)
    past = GroupMotion(traj[:, :20], True, 3.0)
    # the whole decomposition is relative to frame 29; re-anchor its series to frame 19
    c = whole.centroids[20:]
    rel = quat.mul(quat.conj(whole.rotations[19]), whole.rotations[20:])
    r = accumulated_rotvec(np.concatenate([np.array([[1.0, 0, 0, 0]]), rel]))[1:] + past.series[3:, -1]
    pred = past.members(past.series_trajectory(np.concatenate([c.T, r.T])))
    np.testing.assert_allclose(pred[..., :3], traj[:, 20:, :3], atol=1e-9)
    assert np.all(quat.angle_between(pred[..., 3:], traj[:, 20:, 3:]) < 1e-9)


def test_still_part_stays_still_beside_a_moving_part():
    rng = np.random.default_rng(2)
    moving = rigid_box(64, 30)
    body = np.repeat(
        np.concatenate([rng.uniform(-1, 1, (64, 1, 3)), np.tile([1.0, 0, 0, 0], (64, 1, 1))], -1), 30, axis=1
    )
    obs = add_noise(np.concatenate([moving, body]), pos_sigma=5e-4, rot_sigma=0.0, seed=3)
    res = fit_and_rollout("mogaf", obs, 15, PER_GAUSSIAN, seed=0, rigid=False)
    assert res.info["still_fraction"] == pytest.approx(0.5)
    np.testing.assert_allclose(res.poses[64:], np.repeat(obs[64:, -1:], 15, axis=1), atol=1e-12)
    assert np.abs(res.poses[:64, -1, :3] - obs[:64, -1, :3]).max() > 0.1  # the part still moves


def test_still_part_of_a_rigid_flagged_group_stays_still_and_the_body_stays_rigid():
    """A grouping that joins a resting part to a moving box (MuJoCo scene4):
    the resting members keep their last pose, the body's motion (fitted on
    the whole group, as mogaf/forecast/group_motion.py says) is carried to the
    moving members rigidly; the coherence figures see a rigid body and a
    still part, both near zero."""
    rng = np.random.default_rng(2)
    moving = rigid_box(64, 30)
    rest = np.repeat(
        np.concatenate([rng.uniform(-1, 1, (16, 1, 3)) + 2.0, np.tile([1.0, 0, 0, 0], (16, 1, 1))], -1), 30, axis=1
    )
    # orientation jitter above the position's: the rigid path tests positions only
    obs = add_noise(np.concatenate([moving, rest]), pos_sigma=5e-4, rot_sigma=0.02, seed=3)
    res = fit_and_rollout("mogaf", obs, 15, QUICK, seed=0, rigid=True)
    assert res.info["rigid"] is True and res.info["still_fraction"] == pytest.approx(0.2)
    np.testing.assert_allclose(res.poses[64:], np.repeat(obs[64:, -1:], 15, axis=1), atol=1e-12)
    assert _pairwise_change(res.poses[:64], obs[:64, -1]) < 1e-9
    assert np.abs(res.poses[:64, -1, :3] - obs[:64, -1, :3]).max() > 0.1  # the body still moves
    figures = coherence(obs[..., :3], res.poses[..., :3], np.zeros(80, int), np.array([False]), np.array([True]))
    assert figures["still_gaussians"] == 16 and figures["still_displacement"] == 0.0
    assert figures["rigid_distance_change"] < 1e-9
    # moving the resting part with the body (the old rigid path) is what the figures catch
    motion = GroupMotion(obs, True, 0.0)
    carried = motion.members(motion.constant_velocity_trajectory(15))
    moved = coherence(obs[..., :3], carried[..., :3], np.zeros(80, int), np.array([False]), np.array([True]))
    assert moved["still_displacement"] > 0.05


def test_gate_keeps_the_learned_forecaster_only_by_a_margin():
    """A learned forecaster scoring 3 % under constant velocity on the backtest
    (a short fit of a thrown sphere) wins with no margin, not with 10 %; the
    scores recorded are the same either way."""
    obs = add_noise(ballistic_sphere(64, 40), pos_sigma=5e-4, rot_sigma=0.0)
    runs = {
        m: fit_and_rollout(
            "mogaf",
            obs,
            8,
            {
                **QUICK,
                "iterations": 60,
                "structured": {
                    "combine": "select",
                    "backtest_margin": m,
                    "candidates": WITH_VELOCITY,
                    "drift_check": False,
                },
            },
            seed=0,
        )
        for m in (0.0, 0.1)
    }
    learned, cv = runs[0.0].info["backtest_epe_learned"], runs[0.0].info["backtest_epe_constant_velocity"]
    assert 0.9 * cv < learned < cv
    assert runs[0.0].info["choice"] == "learned" and runs[0.1].info["choice"] == "constant_velocity"
    assert runs[0.1].info["backtest_epe_learned"] == learned


def test_gate_freezes_a_group_whose_motion_stopped():
    traj = rigid_box(64, 40)
    obs = np.concatenate([traj[:, :20], np.repeat(traj[:, 19:20], 20, axis=1)], axis=1)  # moves, then rests
    res = fit_and_rollout("mogaf", obs, 10, QUICK, seed=0)
    assert res.info["choice"] == "frozen"
    assert res.info["backtest_epe_frozen"] == 0.0
    np.testing.assert_allclose(res.poses, np.repeat(obs[:, -1:], 10, axis=1), atol=1e-12)  # quaternions renormalised


def test_learned_rigid_forecast_learns_a_fall():
    """A thrown sphere: the channel-wise forecaster learns the parabola that a
    constant velocity misses, and the gate keeps it."""
    traj = ballistic_sphere(64, 48)
    obs, fut = traj[:, :36], traj[:, 36:]
    res = fit_and_rollout("mogaf", obs, 12, {"iterations": 300, "structured": {"candidates": WITH_VELOCITY}}, seed=0)
    cv = fit_and_rollout("constant_velocity", obs, 12)

    def epe(p):
        return np.linalg.norm(p[..., :3] - fut[..., :3], axis=-1).mean()

    assert res.info["choice"] == "learned"
    assert epe(res.poses) < 0.5 * epe(cv.poses)


def test_backtest_weights_are_inverse_squared_errors():
    w = backtest_weights({"frozen": 0.4, "constant_velocity": 0.1, "learned": 0.2})
    np.testing.assert_allclose([w["frozen"], w["constant_velocity"], w["learned"]], np.array([1, 16, 4]) / 21)
    # an exact candidate takes everything; a non-finite one nothing
    assert backtest_weights({"frozen": 0.0, "constant_velocity": 0.1, "learned": 0.0}) == {
        "frozen": 0.5,
        "constant_velocity": 0.0,
        "learned": 0.5,
    }
    assert backtest_weights({"frozen": 0.3, "constant_velocity": 0.3, "learned": float("nan")})["learned"] == 0.0
    with pytest.raises(MogafError, match="non-finite"):
        backtest_weights({"frozen": float("inf"), "learned": float("nan")})


def test_backtest_weights_of_arrays_are_each_elements_weights():
    scores = {
        "frozen": np.array([0.4, 0.0, 0.3, 0.2]),
        "linear_trend": np.array([0.1, 0.1, 0.3, np.nan]),
        "learned": np.array([0.2, 0.0, np.nan, np.inf]),
    }
    w = backtest_weights(scores)
    for i in range(4):
        one = backtest_weights({c: float(v[i]) for c, v in scores.items()})
        assert {c: float(v[i]) for c, v in w.items()} == pytest.approx(one)
    with pytest.raises(MogafError, match="non-finite"):
        backtest_weights({"frozen": np.array([0.1, np.nan]), "learned": np.array([0.2, np.inf])})


def test_neighbour_mean_is_local_and_the_group_mean_when_k_covers_it():
    positions = np.concatenate([np.zeros((5, 3)), np.full((5, 3), 10.0)]) + np.arange(10)[:, None] * 1e-3
    values = np.array([1.0] * 5 + [3.0] * 5)
    np.testing.assert_allclose(neighbour_mean(values, nearest_members(positions, 5)), values)
    assert nearest_members(positions, 12).shape == (10, 10)  # at most the group
    np.testing.assert_allclose(neighbour_mean(values, nearest_members(positions, 10)), 2.0)


def _turned_and_shifted(last: np.ndarray, shift: np.ndarray, turn: np.ndarray) -> np.ndarray:
    """Poses (M, n, 7): every member shifted by shift (n, 3) and turned by turn (n, 4) from `last` (M, 7)."""
    out = np.empty((len(last), len(shift), 7))
    out[..., :3] = last[:, None, :3] + shift[None]
    out[..., 3:] = quat.mul(turn[None], last[:, None, 3:])
    return out


def test_neighbour_smoothed_poses_keep_a_shared_motion_and_average_the_rest_out(monkeypatch):
    rng = np.random.default_rng(0)
    m, n = 400, 6
    last = np.concatenate([rng.uniform(size=(m, 3)), quat.normalize(rng.normal(size=(m, 4)))], axis=-1)
    shift = np.outer(np.arange(1, n + 1), [0.01, -0.02, 0.005])
    turn = quat.from_axis_angle(np.array([0.3, 0.1, 1.0]), np.linspace(0.05, 0.3, n))
    shared = _turned_and_shifted(last, shift, turn)
    neighbours = nearest_members(last[:, :3], 16)
    np.testing.assert_allclose(neighbour_smoothed_poses(shared, last, neighbours), shared, atol=1e-12)
    # a quaternion's sign names no other rotation
    flipped = shared.copy()
    flipped[::3, :, 3:] *= -1.0
    np.testing.assert_allclose(neighbour_smoothed_poses(flipped, last, neighbours), shared, atol=1e-12)
    # each member alone: its own pose
    own = neighbour_smoothed_poses(shared, last, np.arange(m)[:, None])
    np.testing.assert_allclose(own, shared, atol=1e-12)
    # independent jitter on top of the shared motion shrinks about as 1/sqrt(k)
    noisy = shared.copy()
    noisy[..., :3] += rng.normal(scale=0.01, size=(m, n, 3))
    smoothed = neighbour_smoothed_poses(noisy, last, neighbours)
    before = np.abs(noisy[..., :3] - shared[..., :3]).std()
    after = np.abs(smoothed[..., :3] - shared[..., :3]).std()
    assert after < 0.4 * before
    # an affine field (a small body rotation's displacements) is kept but for the slopes' small ridge
    rotation = quat.from_axis_angle(np.array([0.0, 0.0, 1.0]), np.linspace(0.01, 0.06, n))
    centre = last[:, :3].mean(0)
    turning = shared.copy()
    turning[..., :3] = centre + quat.rotate(rotation[None], last[:, None, :3] - centre)
    kept = neighbour_smoothed_poses(turning, last, neighbours)
    motion = np.abs(turning[..., :3] - last[:, None, :3]).max()
    assert np.abs(kept[..., :3] - turning[..., :3]).max() < 0.01 * motion
    # members taken in passes (a big group): the same fit, bit for bit
    monkeypatch.setattr(candidates, "LOCAL_LINEAR_CHUNK", 16 * 6 * 7 * 5)
    np.testing.assert_array_equal(neighbour_smoothed_poses(noisy, last, neighbours), smoothed)
    # two members in one place turning the same angle in opposite senses: no mean turn, none
    pair = _turned_and_shifted(last[:2], np.zeros((1, 3)), quat.from_axis_angle(np.array([0, 0, 1.0]), [0.2]))
    pair[1, :, 3:] = quat.mul(quat.from_axis_angle(np.array([0, 0, 1.0]), -0.2), last[1, 3:])[None]
    pair[1, :, :3] = pair[0, :, :3]
    pair_last = last[:2].copy()
    pair_last[1, :3] = pair_last[0, :3]
    both = np.array([[0, 1], [1, 0]])
    np.testing.assert_allclose(neighbour_smoothed_poses(pair, pair_last, both), pair_last[:, None], atol=1e-12)


def _neighbour_change(poses: np.ndarray, last: np.ndarray, k: int = 8) -> float:
    """Mean |d_ij(end) - d_ij(T)| over each member's k nearest at the last observed frame: local tearing."""
    nb = nearest_members(last[:, :3], k + 1)[:, 1:]
    before = np.linalg.norm(last[:, None, :3] - last[nb, :3], axis=-1)
    after = np.linalg.norm(poses[:, None, -1, :3] - poses[nb, -1, :3], axis=-1)
    return float(np.abs(after - before).mean())


def test_coherent_neighbours_hold_a_noisy_surface_together_and_leave_rigid_groups_alone():
    """Each Gaussian of a jittered sheet extrapolates its own jitter; the
    local affine fit keeps the sheet's local structure, and its forecast of
    the travelling wave stays about as close to the truth."""
    truth = waving_sheet(600, 40)
    obs = add_noise(truth[:, :32], pos_sigma=0.004, rot_sigma=0.0)
    own = fit_and_rollout("mogaf", obs, 8, PER_GAUSSIAN, seed=1, rigid=False)
    coherent = fit_and_rollout(
        "mogaf",
        obs,
        8,
        {**QUICK, "structured": {"nonrigid_motion": "per_gaussian", "coherent_neighbors": 16}},
        seed=1,
        rigid=False,
    )
    assert coherent.info["coherent_neighbors"] == 16 and "coherent_neighbors" not in own.info
    assert _neighbour_change(coherent.poses, obs[:, -1]) < 0.5 * _neighbour_change(own.poses, obs[:, -1])
    error = {
        name: np.linalg.norm(res.poses[..., :3] - truth[:, 32:, :3], axis=-1).mean()
        for name, res in (("own", own), ("coherent", coherent))
    }
    assert error["coherent"] < 1.01 * error["own"]
    # a rigid group is one motion already: the same forecast, bit for bit
    box = add_noise(rigid_box(128, 30), pos_sigma=0.002, rot_sigma=0.0)
    plain = fit_and_rollout("mogaf", box, 10, QUICK, seed=0, rigid=True).poses
    smoothed = fit_and_rollout(
        "mogaf", box, 10, {**QUICK, "structured": {"coherent_neighbors": 16}}, seed=0, rigid=True
    )
    np.testing.assert_array_equal(smoothed.poses, plain)


def test_blend_with_member_weights_blends_each_row_on_its_own():
    rng = np.random.default_rng(2)
    a, b = (np.concatenate([rng.normal(size=(4, 5, 3)), quat.normalize(rng.normal(size=(4, 5, 4)))], -1) for _ in "ab")
    w = np.array([[1.0, 0.0, 0.3, 0.5], [0.0, 1.0, 0.7, 0.5]])
    got = blend_trajectories([a, b], w)
    for m in range(4):
        np.testing.assert_allclose(got[m], blend_trajectories([a[m], b[m]], w[:, m]), atol=1e-12)
    np.testing.assert_allclose(got[0], a[0], atol=1e-12)
    np.testing.assert_allclose(got[1, :, :3], b[1, :, :3], atol=1e-12)


def test_member_backtest_weighs_each_part_of_a_non_rigid_group_by_its_own_motion():
    """One non-rigid group of two parts 10 m apart: a flap swaying about its
    rest pose (frozen is right to within the sway) and a copy sliding
    uniformly (the line through each series is exact); a third copy, 20 m
    away, never moves (still members: not weighted, kept still). Weighted per group,
    one blend serves both: the line carries the flap off along its last
    swing and the other candidates pull the slider off its line. Weighted
    per member (backtest_neighbors under a part's size), frozen is the
    flap's heaviest candidate and the line takes all of the slider."""
    base = _resting_box(24, 1, 0)[:, :1]  # one pose per member
    t = np.arange(40, dtype=np.float64)
    flap = np.repeat(base, 40, axis=1)
    flap[..., 0] += 0.05 * np.sin(2.0 * np.pi * t / 12.0)
    sliding = np.repeat(base, 40, axis=1)
    sliding[..., :3] += 10.0 + t[None, :, None] * np.array([0.02, -0.01, 0.005])
    resting = np.repeat(base, 40, axis=1)
    resting[..., :3] -= 20.0
    resting[..., 3:] = [1.0, 0.0, 0.0, 0.0]  # exactly constant: no rounding in its turn either
    traj = np.concatenate([flap, sliding, resting])
    obs, fut = traj[:, :30], traj[:, 30:]

    def epe(poses, part):
        return np.linalg.norm(poses[part, :, :3] - fut[part, :, :3], axis=-1).mean()

    flap_part, slider = slice(0, 24), slice(24, 48)
    model, info = _fit_structured(
        obs, {**QUICK, "structured": {"nonrigid_motion": "per_gaussian", "backtest_neighbors": 8}}, 0, False, 10
    )
    assert info["backtest_neighbors"] == 8 and not info["rigid"]
    assert _fit_structured(obs, PER_GAUSSIAN, 0, False, 10)[1]["backtest_neighbors"] == 32  # the default
    assert isinstance(model, WeightedCandidates)
    np.testing.assert_array_equal(model.motion.moving, np.arange(48))  # the resting copy is still
    assert model.weights.shape == (len(model.candidates), 48)
    names = [c.name for c in model.candidates]
    frozen_w, trend_w = model.weights[names.index("frozen")], model.weights[names.index("linear_trend")]
    assert np.all(np.argmax(model.weights[:, flap_part], axis=0) == names.index("frozen"))
    assert np.all(trend_w[slider] > 0.999)
    # the group's figures are the members' mean weights
    assert info["backtest_weight_frozen"] == pytest.approx(frozen_w.mean())
    poses = model.rollout(10)
    np.testing.assert_array_equal(poses[48:], np.repeat(obs[48:, -1:], 10, axis=1))
    per_group, group_info = _fit_structured(
        obs, {**QUICK, "structured": {"nonrigid_motion": "per_gaussian", "backtest_neighbors": 0}}, 0, False, 10
    )
    assert "backtest_neighbors" not in group_info
    group_poses = per_group.rollout(10)
    assert epe(poses, flap_part) < 0.8 * epe(group_poses, flap_part)
    assert epe(poses, slider) < 1e-9 < 1e-3 < epe(group_poses, slider)
    # neighbourhoods covering the moving members: the group's own weighting, exactly
    whole, whole_info = _fit_structured(
        obs, {**QUICK, "structured": {"nonrigid_motion": "per_gaussian", "backtest_neighbors": 48}}, 0, False, 10
    )
    assert {k: v for k, v in whole_info.items() if k != "final_loss"} == {
        k: v for k, v in group_info.items() if k != "final_loss"
    }
    np.testing.assert_array_equal(whole.rollout(10), group_poses)


def test_blend_of_rigid_poses_is_one_rigid_pose_between_them():
    """Two rotations about one axis blend, with equal weights, to the middle
    angle, whatever the quaternions' signs; members carried by the blended
    pose keep their distances."""
    n = 6
    angles = np.linspace(0.1, 0.6, n)
    z = np.broadcast_to([0.0, 0.0, 1.0], (n, 3))
    a = np.concatenate([np.zeros((n, 3)), quat.from_axis_angle(z, angles)], axis=-1)
    b = np.concatenate([np.ones((n, 3)), -quat.from_axis_angle(z, 3 * angles)], axis=-1)  # other hemisphere
    mid = blend_trajectories([a, b], np.array([0.5, 0.5]))
    np.testing.assert_allclose(mid[:, :3], 0.5, atol=1e-12)
    assert np.all(quat.angle_between(mid[:, 3:], quat.from_axis_angle(z, 2 * angles)) < 1e-9)
    motion = GroupMotion(rigid_box(40, 12), True, 3.0)
    carried = motion.members(mid)
    assert _pairwise_change(carried, motion.last) < 1e-9


def _resting_box(g: int, moving: int, resting: int) -> np.ndarray:
    traj = rigid_box(g, moving)
    return np.concatenate([traj, np.repeat(traj[:, -1:], resting, axis=1)], axis=1)  # moves, then rests


def test_weighted_combination_blends_the_candidates_and_stays_rigid():
    obs = add_noise(rigid_box(64, 30), pos_sigma=0.002, rot_sigma=0.0)
    settings = {**QUICK, "structured": {"combine": "weighted"}}  # the default
    res = fit_and_rollout("mogaf", obs, 12, settings, seed=0)
    info = res.info
    weights = {c: info[f"backtest_weight_{c}"] for c in DEFAULT_CANDIDATES}
    assert sum(weights.values()) == pytest.approx(1.0)
    assert info["choice"] == max(weights, key=weights.get)
    # the learned candidate is scored with its refit drift (drift_check, on by default)
    assert weights == pytest.approx(_weights_of_the_scores(info))
    assert _pairwise_change(res.poses, obs[:, -1]) < 1e-9
    # the blend lies between the candidates: not the selected one alone
    chosen = fit_and_rollout("mogaf", obs, 12, {**QUICK, "structured": {"combine": "select"}}, seed=0)
    assert chosen.info["backtest_epe_learned"] == info["backtest_epe_learned"]
    assert np.abs(res.poses[..., :3] - chosen.poses[..., :3]).max() > 1e-6


def test_weighted_blend_is_the_weighted_mean_of_the_candidates_forecasts():
    """Checked against each candidate's own member forecast (the path select
    rolls out): every member of this box moves, so the blended group's mean
    position is the weighted mean of the candidates' mean positions, and each
    member turns by the weighted quaternion mean of the candidates' turns."""
    obs = add_noise(rigid_box(48, 30), pos_sigma=0.002, rot_sigma=0.0)
    blend, info = _fit_structured(obs, {**QUICK, "structured": {"combine": "weighted"}}, 0, True, 12)
    assert isinstance(blend, WeightedCandidates) and len(blend.candidates) == len(DEFAULT_CANDIDATES)
    assert blend.motion.still.sum() == 0
    poses = blend.rollout(12)
    each = [c.rollout(12) for c in blend.candidates]
    w = blend.weights
    want_mean = sum(wi * p[..., :3].mean(axis=0) for wi, p in zip(w, each))
    np.testing.assert_allclose(poses[..., :3].mean(axis=0), want_mean, atol=1e-9)
    turns = [quat.mul(p[..., 3:], quat.conj(obs[:, -1:, 3:])) for p in each]
    ref = turns[int(np.argmax(w))]
    want_turn = quat.normalize(sum(wi * quat.align_to(t, ref) for wi, t in zip(w, turns)))
    got_turn = quat.mul(poses[..., 3:], quat.conj(obs[:, -1:, 3:]))
    assert np.all(quat.angle_between(got_turn, want_turn) < 1e-7)


def test_an_exact_backtest_takes_all_the_weight():
    """A box that moved, then rested through the backtest: frozen's backtest
    is exact, the moving candidates' are not, so the forecast is frozen's,
    exactly."""
    obs = _resting_box(64, 30, 10)  # a 10-step forecast backtests the last 10 frames
    res = fit_and_rollout("mogaf", obs, 10, {**QUICK, "structured": {"combine": "weighted"}}, seed=0)
    assert res.info["backtest_epe_frozen"] == 0.0 and res.info["backtest_epe_linear_trend"] > 1e-3
    assert res.info["backtest_weight_frozen"] == 1.0 and res.info["choice"] == "frozen"
    np.testing.assert_array_equal(res.poses[..., :3], np.repeat(obs[:, -1:, :3], 10, axis=1))
    np.testing.assert_allclose(res.poses, np.repeat(obs[:, -1:], 10, axis=1), atol=1e-12)  # quaternions renormalised


def test_origin_frames_halve_down_to_two():
    assert origin_frames(14, 1) == [14]
    assert origin_frames(14, 3) == [14, 7, 4]
    assert origin_frames(14, 9) == [14, 7, 4, 2]  # at least 2 frames, each origin later than the one before
    assert origin_frames(5, 4) == [5, 2]
    assert origin_frames(2, 3) == [2] and origin_frames(1, 3) == [1]


def _stopped_box(resting: int) -> np.ndarray:
    """A box that moves steadily, then rests for its last `resting` frames, seen with noise."""
    traj = rigid_box(64, 44)
    obs = np.concatenate([traj, np.repeat(traj[:, -1:], resting, axis=1)], axis=1)
    return add_noise(obs, pos_sigma=0.002, rot_sigma=0.0)


def test_later_backtest_origins_see_a_stop_the_first_window_does_not():
    """The box stops 5 frames before the end; a 12-step forecast backtests
    the last 12, where the stop is a small part: from that origin the line
    wins. The origins that hold back 6 and 3 frames see the stop: frozen
    scores best there, takes the most weight on average over the three, and
    the forecast stays nearer the last pose. Each weight is the mean of the
    origins' own inverse-squared-error weights."""
    obs = _stopped_box(5)
    runs = {
        n: fit_and_rollout("mogaf", obs, 12, {**QUICK, "structured": {"backtest_origins": n}}, seed=0) for n in (1, 3)
    }
    one, three = runs[1].info, runs[3].info
    assert "backtest_origins" not in one and three["backtest_origins"] == 3
    assert one["choice"] == "linear_trend" and three["choice"] == "frozen"
    # the first origin is the same backtest either way
    for c in DEFAULT_CANDIDATES:
        assert three[f"backtest_epe_{c}"] == one[f"backtest_epe_{c}"]
    for n in (6, 3):
        assert three[f"backtest_epe_frozen_last{n}"] < three[f"backtest_epe_linear_trend_last{n}"]
    per_origin = [_weights_of_the_scores(three)]
    for n in (6, 3):
        scores = {c: three[f"backtest_epe_{c}_last{n}"] for c in DEFAULT_CANDIDATES}
        scores["learned"] = float(np.hypot(scores["learned"], three[f"learned_refit_drift_last{n}"]))
        per_origin.append(backtest_weights(scores))
    want = {c: np.mean([w[c] for w in per_origin]) for c in DEFAULT_CANDIDATES}
    assert {c: three[f"backtest_weight_{c}"] for c in DEFAULT_CANDIDATES} == pytest.approx(want)

    def travel(res):
        return np.linalg.norm(res.poses[:, -1, :3] - obs[:, -1, :3], axis=-1).mean()

    assert travel(runs[3]) < 0.5 * travel(runs[1])


def test_later_backtest_origins_keep_a_steady_motion_moving():
    """On a box that slides and spins steadily to the end, every origin says
    the same: frozen keeps almost no weight and the forecast is about the
    single window's."""
    obs = add_noise(_uniform_box(48, 40), pos_sigma=0.002, rot_sigma=0.0)
    fut = _uniform_box(48, 52)[:, 40:]
    runs = {
        n: fit_and_rollout("mogaf", obs, 12, {**QUICK, "structured": {"backtest_origins": n}}, seed=0, rigid=True)
        for n in (1, 3)
    }
    assert runs[3].info["backtest_weight_frozen"] < 0.05

    def epe(res):
        return np.linalg.norm(res.poses[..., :3] - fut[..., :3], axis=-1).mean()

    assert epe(runs[3]) < 1.2 * epe(runs[1]) + 1e-3


def test_info_records_the_decision():
    obs = rigid_box(32, 24)
    info = fit_and_rollout("mogaf", obs, 4, QUICK, seed=0).info
    for key in (
        "mode",
        "rigid",
        "rigid_residual_rel",
        "rigid_source",
        "choice",
        "backtest_frames",
        "backtest_epe_learned",
        "backtest_epe_linear_trend",
        "backtest_epe_frozen",
        "learned_refit_drift",
        "still_fraction",
        "iterations",
    ):
        assert key in info, key
    assert info["mode"] == "structured" and info["rigid_source"] == "residual"
    for other in ("constant_velocity", "constant_acceleration"):  # not default candidates
        assert f"backtest_epe_{other}" not in info
    # the backtest's network, then the refit the drift check compares it with (kept, not fitted again)
    assert info["iterations"] == 2 * QUICK["iterations"]
    two = fit_and_rollout("mogaf", obs, 4, {**QUICK, "structured": {"refit_networks": 2}}, seed=0).info
    assert two["iterations"] == 3 * QUICK["iterations"]


def test_refit_networks_average_networks_fitted_from_their_own_seeds():
    obs = rigid_box(24, 30)
    run = load_run("mogaf", MOGAF_DEFAULTS, {**QUICK, "structured": {"refit_networks": 2}}, {})
    motion = GroupMotion(obs, True, run.own.still_factor)
    mean = refitted_learned(motion, run, 5, "cpu", rollout_steps=4)
    one = [FittedCandidate("learned", motion, run, 5 + k * REFIT_SEED_STRIDE) for k in range(2)]
    assert mean.info["iterations"] == 2 * QUICK["iterations"] and mean.info["final_loss"] == one[0].info["final_loss"]
    np.testing.assert_array_equal(mean.series_future(4), np.mean([c.series_future(4) for c in one], axis=0))
    assert np.abs(one[0].series_future(4) - one[1].series_future(4)).max() > 0  # two fits, two forecasts
    # the default, one network: that network's forecast
    single = load_run("mogaf", MOGAF_DEFAULTS, QUICK, {})
    np.testing.assert_array_equal(refitted_learned(motion, single, 5, "cpu").series_future(4), one[0].series_future(4))
    # a group whose every Gaussian is still has no series and fits no network
    jitter = add_noise(np.repeat(obs[:, -1:], 30, axis=1), pos_sigma=1e-4, rot_sigma=1e-4)
    assert refitted_learned(GroupMotion(jitter, False, run.own.still_factor), run, 5, "cpu").model is None
    with pytest.raises(MogafError, match="a mean of no networks"):
        NetworkMean(())


def test_short_observations_fall_back_without_failing():
    obs = rigid_box(16, 3)
    res = fit_and_rollout("mogaf", obs, 5, QUICK, seed=0)
    assert np.isfinite(res.poses).all() and "backtest_frames" not in res.info
    assert res.info["choice"] == "constant_velocity"  # nothing shows the learned one is better


def test_paper_mode_is_selectable_and_equals_mogaf_paper():
    obs = rigid_box(48, 16)
    a = fit_and_rollout("mogaf", obs, 4, {**QUICK, "mode": "paper"}, seed=1)
    b = fit_and_rollout("mogaf_paper", obs, 4, QUICK, seed=1)
    np.testing.assert_array_equal(a.poses, b.poses)
    assert "choice" not in a.info
    # mogaf_paper ignores a structured mode asked of it
    c = fit_and_rollout("mogaf_paper", obs, 4, {**QUICK, "mode": "structured"}, seed=1)
    np.testing.assert_array_equal(a.poses, c.poses)


def test_the_mode_picks_the_forecaster_class():
    from mogaf.forecast.registry import load_settings
    from mogaf.forecast.transformer import MoGaFForecaster, MoGaFPaperForecaster

    assert type(make_forecaster("mogaf")) is StructuredMoGaF
    assert type(make_forecaster("mogaf", {"mode": "paper"})) is MoGaFForecaster
    assert type(make_forecaster("mogaf_paper", {"mode": "structured"})) is MoGaFPaperForecaster
    # settings loaded once are passed on as they are, and still pick the class
    assert type(make_forecaster("mogaf", load_settings("mogaf", {"mode": "paper"}))) is MoGaFForecaster
    with pytest.raises(MogafError, match="run by StructuredMoGaF, not MoGaFForecaster"):
        MoGaFForecaster({})


def test_the_structured_fit_fits_and_the_rollout_only_rolls_out():
    """Everything is decided and trained in fit (for the horizon it is given);
    rollout rolls the refit candidates out, the same poses every time."""
    obs = rigid_box(32, 24)
    fc = make_forecaster("mogaf", QUICK, seed=0).fit(obs, horizon=6)
    assert fc.info["choice"] in DEFAULT_CANDIDATES and fc.info["iterations"] == 2 * QUICK["iterations"]
    trained = dict(fc.info)
    first = fc.rollout(6)
    np.testing.assert_array_equal(fc.rollout(6), first)
    assert {k: v for k, v in fc.info.items() if k != "rollout_time_s"} == trained
    np.testing.assert_array_equal(fit_and_rollout("mogaf", obs, 6, QUICK, seed=0).poses, first)


def test_the_refit_network_rolls_out_once_and_the_forecast_reuses_its_steps(monkeypatch):
    """The drift check's refit rolls out the forecast's length at once (its
    backtest window is shorter) and the forecast reads those kept steps: the
    same poses as when every rollout is computed afresh, one rollout fewer."""
    from mogaf.forecast.candidates import FittedCandidate
    from mogaf.forecast.channel_net import ChannelForecaster

    obs = waving_sheet(32, 24)
    quick = {**PER_GAUSSIAN, "iterations": 20}
    calls = []
    rollout = ChannelForecaster.rollout

    def counted(self, series, floor, n):
        calls.append(n)
        return rollout(self, series, floor, n)

    monkeypatch.setattr(ChannelForecaster, "rollout", counted)
    fc = make_forecaster("mogaf", quick, seed=0).fit(obs, rigid=False, horizon=20)
    assert fc.info["backtest_frames"] < 20 and fc.info["backtest_weight_learned"] > 0.0  # the refit is in the forecast
    kept = fc.rollout(20)
    kept_calls, calls[:] = list(calls), []
    monkeypatch.setattr(
        FittedCandidate, "series_future", lambda self, n: self.model.rollout(self.motion.series, self.motion.floor, n)
    )
    fresh = make_forecaster("mogaf", quick, seed=0).fit(obs, rigid=False, horizon=20).rollout(20)
    np.testing.assert_array_equal(kept, fresh)
    assert len(kept_calls) == len(calls) - 1 and 20 in kept_calls and calls.count(20) == 1


def test_bad_structured_settings_are_refused_by_name():
    """When the settings are loaded: before anything is fitted."""
    with pytest.raises(MogafError, match="mode"):
        make_forecaster("mogaf", {"mode": "fancy"})
    with pytest.raises(MogafError, match="structured.*contxt"):
        make_forecaster("mogaf", {"structured": {"contxt": 4}})
    with pytest.raises(MogafError, match="backtest_frac"):
        make_forecaster("mogaf", {"structured": {"backtest_frac": 1.5}})
    with pytest.raises(MogafError, match="context"):
        make_forecaster("mogaf", {"structured": {"context": 1}})
    with pytest.raises(MogafError, match="combine"):
        make_forecaster("mogaf", {"structured": {"combine": "mean"}})
    with pytest.raises(MogafError, match="backtest_origins"):
        make_forecaster("mogaf", {"structured": {"backtest_origins": 0}})
    with pytest.raises(MogafError, match="trend_window"):
        make_forecaster("mogaf", {"structured": {"trend_window": 1}})
    with pytest.raises(MogafError, match="backtest_margin applies to combine: select"):
        make_forecaster("mogaf", {"structured": {"backtest_margin": 0.1}})
    for bad in (["frozen", "kalman"], [], ["frozen", "frozen"]):
        with pytest.raises(MogafError, match="candidates must be distinct names"):
            make_forecaster("mogaf", {"structured": {"candidates": bad}})


# ---------------------------------------------------------------- settings without effect
def _inert_keys(methods: list[str], section: dict) -> set[str]:
    return {key for key, _ in inert_settings({"methods": methods, "mogaf": section})}


_SHEET_POSES: dict[str, np.ndarray] = {}


def _sheet_poses(section: dict) -> np.ndarray:
    """MoGaF's forecast of a waving sheet with these settings (over QUICK),
    fitted once per distinct settings: fits are deterministic for a seed, and
    the cases below share their controls."""
    key = json.dumps(section, sort_keys=True)
    if key not in _SHEET_POSES:
        # per Gaussian, where every rule can act
        structured = {"nonrigid_motion": "per_gaussian", **section.get("structured", {})}
        poses = fit_and_rollout(
            "mogaf", waving_sheet(48, 24), 6, {**QUICK, **section, "structured": structured}, seed=3
        ).poses
        poses.setflags(write=False)
        _SHEET_POSES[key] = poses
    return _SHEET_POSES[key]


def _changed(section: dict, change: dict, key: str) -> dict:
    if key.startswith("structured."):
        return {**section, "structured": {**section.get("structured", {}), **change}}
    return {**section, **change}


@pytest.mark.parametrize(
    "base, control, change, key",
    [
        ({"structured": {"candidates": WITH_VELOCITY}}, {}, {"trend_window": 12}, "structured.trend_window"),
        (
            {},
            {"structured": {"candidates": ["frozen", "damped_trend", "learned"]}},
            {"trend_half_life": 2.0},
            "structured.trend_half_life",
        ),
        ({"structured": {"combine": "select"}}, {}, {"backtest_neighbors": 4}, "structured.backtest_neighbors"),
        ({"structured": {"combine": "select"}}, {}, {"backtest_origins": 3}, "structured.backtest_origins"),
        ({"structured": {"gate": False}}, {}, {"drift_check": False}, "structured.drift_check"),
        ({"structured": {"gate": False}}, {}, {"backtest_frac": 0.1}, "structured.backtest_frac"),
        ({"structured": {"candidates": ["frozen", "linear_trend"]}}, {}, {"horizon": 4}, "structured.horizon"),
        ({"mode": "paper"}, {}, {"context": 4}, "structured.context"),
        ({}, {"mode": "paper"}, {"weight_decay": 0.1}, "weight_decay"),
        ({"masking": False}, {}, {"mask_ratio_start": 0.2}, "mask_ratio_start"),
        (
            {"structured": {"combine": "select", "candidates": ["frozen", "linear_trend"]}},
            {"structured": {"combine": "select"}},
            {"backtest_margin": 0.99},
            "structured.backtest_margin",
        ),
    ],
)
def test_a_setting_said_to_have_no_effect_changes_no_forecast(base, control, change, key):
    """What inert_settings lists must be true: the same forecast with and
    without the value (a non-rigid group, where every rule can act), and,
    where the setting that silences it is left at its default (`control`),
    a different one and no line."""
    poses = _sheet_poses
    before, after = base, _changed(base, change, key)
    assert _inert_keys(["mogaf"], after) - _inert_keys(["mogaf"], before) == {key}
    np.testing.assert_array_equal(poses(before), poses(after))
    assert key not in _inert_keys(["mogaf"], _changed(control, change, key))
    assert np.abs(poses(control) - poses(_changed(control, change, key))).max() > 1e-6


def test_inert_settings_count_every_method_that_reads_forecast_mogaf():
    # mogaf_paper reads forecast.mogaf in paper mode, without `structured`
    assert _inert_keys(["mogaf"], {"weight_decay": 0.1}) == {"weight_decay"}
    assert _inert_keys(["mogaf", "mogaf_paper"], {"weight_decay": 0.1}) == set()
    assert _inert_keys(["mogaf_paper"], {"structured": {"context": 4}, "lr": 0.01}) == {"structured.context"}
    assert _inert_keys(["frozen"], {"lr": 0.01}) == {"lr"}
    assert _inert_keys(["mogaf_paper"], {"mode": "paper"}) == {"mode"}
    # masking's settings without masking, in both modes
    assert _inert_keys(["mogaf", "mogaf_paper"], {"masking": False, "mask_ratio_start": 0.2}) == {"mask_ratio_start"}
    # a learned-free candidate list leaves the network's settings unread, not the parabola's context
    no_net = {"lr": 0.01, "structured": {"candidates": ["frozen", "constant_acceleration"], "context": 8}}
    assert _inert_keys(["mogaf"], no_net) == {"lr"}
    no_net["structured"]["refit_networks"] = 2
    assert _inert_keys(["mogaf"], no_net) == {"lr", "structured.refit_networks"}
    # the defaults, and a candidate list in another order, list nothing
    assert inert_settings({"methods": ["mogaf"], "mogaf": {}}) == []
    assert _inert_keys(["mogaf"], {"structured": {"candidates": DEFAULT_CANDIDATES[::-1]}}) == set()
    ((_, line),) = inert_settings({"methods": ["mogaf"], "mogaf": {"structured": {"gate": False, "trend_window": 5}}})
    assert line == "forecast.mogaf.structured.trend_window = 5 has no effect: gate is false (no backtest)"


# ---------------------------------------------------------------- polynomial candidates
def test_local_polynomial_continues_its_curve_exactly_and_averages_jitter_out():
    t = np.arange(20, dtype=np.float64)
    series = np.stack([3.0 - 0.5 * t + 0.02 * t**2, 1.0 + 0.1 * t, np.full(20, 7.0)])
    future = np.arange(20, 32, dtype=np.float64)
    want = np.stack([3.0 - 0.5 * future + 0.02 * future**2, 1.0 + 0.1 * future, np.full(12, 7.0)])
    np.testing.assert_allclose(local_polynomial(series, 16, 2, 12), want, atol=1e-9)
    # a line continues the lines exactly (the parabola is no line: its row is not)
    np.testing.assert_allclose(local_polynomial(series, 8, 1, 12)[1:], want[1:], atol=1e-9)
    # short series: a line through two values, the value itself for one
    np.testing.assert_allclose(local_polynomial(np.array([[1.0, 3.0]]), 16, 2, 3), [[5.0, 7.0, 9.0]])
    np.testing.assert_allclose(local_polynomial(np.array([[4.0]]), 16, 1, 2), [[4.0, 4.0]])
    # a jittered last frame moves the two-frame velocity by the jitter, either fit by much less
    rng = np.random.default_rng(0)
    line = 0.01 * np.arange(30, dtype=np.float64)
    noisy = line + rng.normal(0.0, 1e-3, 30)
    noisy[-1] += 5e-3
    truth = 0.01 * np.arange(30, 42, dtype=np.float64)
    velocity_err = np.abs(noisy[-1] + (noisy[-1] - noisy[-2]) * np.arange(1, 13) - truth).max()
    for window, degree in ((16, 2), (8, 1)):
        fit_err = np.abs(local_polynomial(noisy[None], window, degree, 12)[0] - truth).max()
        assert fit_err < 0.5 * velocity_err, (window, degree)


def _uniform_box(g: int, t: int) -> np.ndarray:
    """A box sliding at a constant velocity while it spins at a constant rate
    about its own centre: each series (centroid, accumulated rotation vector)
    is a line, though the body's twist is not constant."""
    from mogaf.forecast.synthetic import rigid_motion

    rng = np.random.default_rng(4)
    pts = rng.uniform(-0.2, 0.2, (g, 3))
    pts -= pts.mean(axis=0)  # it spins about its centroid
    q0 = quat.canonical_sign(quat.normalize(rng.normal(size=(g, 4))))
    k = np.arange(t, dtype=np.float64)
    rot = quat.from_axis_angle(np.broadcast_to([0.3, 1.0, -0.2], (t, 3)), 0.06 * k)
    return rigid_motion(pts, q0, np.zeros(3), rot, k[:, None] * np.array([0.02, -0.01, 0.005]))


def test_linear_trend_is_exact_on_uniform_motion_and_steadier_than_the_last_step():
    """The linear_trend candidate continues a sliding, spinning box exactly and
    rigidly; when the last observed frame is off (a reconstruction's least
    constrained frame), it moves much less than the last step's velocity does."""
    traj = _uniform_box(48, 40)
    obs, fut = traj[:, :30], traj[:, 30:]
    settings = {**QUICK, "structured": {"candidates": ["linear_trend"]}}
    trend, info = _fit_structured(obs, settings, 0, True, 10)
    poses = trend.rollout(10)
    np.testing.assert_allclose(poses[..., :3], fut[..., :3], atol=1e-9)
    assert np.all(quat.angle_between(poses[..., 3:], fut[..., 3:]) < 1e-9)
    assert info["iterations"] == 0 and _pairwise_change(poses, obs[:, -1]) < 1e-9
    # the last frame displaced by 1.5 steps' travel along x
    bad = obs.copy()
    bad[:, -1, 0] += 0.03

    def epe(p):
        return np.linalg.norm(p[..., :3] - fut[..., :3], axis=-1).mean()

    trend_err = epe(_fit_structured(bad, settings, 0, True, 10)[0].rollout(10))
    velocity_err = epe(fit_and_rollout("constant_velocity", bad, 10).poses)
    assert trend_err < 0.25 * velocity_err


def test_damped_steps_and_time_warp_give_a_damped_trend():
    """Read at damped steps, a uniform motion becomes Gardner and McKenzie's
    damped trend (each step's displacement phi times the previous one's);
    undamped steps give the trajectory back, and quaternions stay unit."""
    np.testing.assert_array_equal(damped_steps(5, 1.0), [1, 2, 3, 4, 5])
    steps = damped_steps(6, 0.8)
    np.testing.assert_allclose(np.diff(np.concatenate([[0.0], steps])), 0.8 ** np.arange(6), rtol=1e-15)
    start = np.array([[0.0, 1.0, 2.0, 1.0, 0.0, 0.0, 0.0]])
    k = np.arange(1, 7, dtype=np.float64)
    turn = quat.from_axis_angle(np.broadcast_to([0.0, 0.0, 1.0], (6, 3)), 0.1 * k)
    traj = np.concatenate([start[:, None, :3] + k[None, :, None] * [0.1, 0.0, -0.2], turn[None]], -1)
    np.testing.assert_allclose(time_warped(traj, start, damped_steps(6, 1.0)), traj, atol=1e-15)
    warped = time_warped(traj, start, steps)
    np.testing.assert_allclose(warped[0, :, :3], start[:, :3] + steps[:, None] * [0.1, 0.0, -0.2], atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(warped[..., 3:], axis=-1), 1.0, atol=1e-14)
    angle = quat.angle_between(warped[0, :, 3:], np.array([1.0, 0.0, 0.0, 0.0]))
    np.testing.assert_allclose(angle, 0.1 * steps, atol=1e-4)  # nlerp between steps 0.1 rad apart


def test_damping_slows_a_forecast_and_keeps_rigid_groups_rigid_and_still_parts_still():
    """structured.damping (speed halving every damping x T frames): a moving
    box's centre covers the damped trend's share of the undamped forecast's
    ground (uniform motion); beside a resting part, the body stays rigid and
    the part still; 0 is the undamped forecast to the bit."""
    box = rigid_box(64, 30)
    lin = {**QUICK, "structured": {"candidates": ["linear_trend"]}}

    def forecast(obs, **structured):
        section = {**lin, "structured": {**lin["structured"], **structured}}
        return fit_and_rollout("mogaf", obs, 15, section, seed=0, rigid=True).poses

    plain, damped = forecast(box), forecast(box, damping=0.5)
    np.testing.assert_array_equal(forecast(box, damping=0.0), plain)
    centre = box[:, -1, :3].mean(0)
    ground = np.linalg.norm(damped[:, -1, :3].mean(0) - centre)
    full = np.linalg.norm(plain[:, -1, :3].mean(0) - centre)
    share = damped_steps(15, 0.5 ** (1 / 15))[-1] / 15  # half-life 0.5 x 30 observed frames
    assert ground == pytest.approx(share * full, rel=0.02) and share < 0.75

    rng = np.random.default_rng(2)
    rest = np.repeat(
        np.concatenate([rng.uniform(-1, 1, (16, 1, 3)) + 2.0, np.tile([1.0, 0, 0, 0], (16, 1, 1))], -1), 30, axis=1
    )
    poses = forecast(np.concatenate([box, rest]), damping=0.5)
    assert _pairwise_change(poses[:64], box[:, -1]) < 1e-9
    np.testing.assert_array_equal(poses[64:], np.repeat(rest[:, -1:], 15, axis=1))


def _sliding_box(g: int, t: int, speed_of_step) -> np.ndarray:
    """A box sliding along x, its step k's length speed_of_step(k)."""
    from mogaf.forecast.synthetic import rigid_motion

    rng = np.random.default_rng(5)
    pts = rng.uniform(-0.2, 0.2, (g, 3))
    q0 = quat.canonical_sign(quat.normalize(rng.normal(size=(g, 4))))
    path = np.concatenate([[0.0], np.cumsum(speed_of_step(np.arange(1, t, dtype=np.float64)))])
    identity = np.tile([1.0, 0.0, 0.0, 0.0], (t, 1))
    return rigid_motion(pts, q0, np.zeros(3), identity, path[:, None] * np.array([1.0, 0.0, 0.0]))


def test_damped_trend_candidate_slows_the_line_and_wins_the_backtest_only_where_motion_slows():
    """damped_trend is linear_trend's line read at damped steps (speed halving
    every trend_half_life steps), rigid groups staying rigid. In the backtest
    it beats the line and frozen on a box whose speed decays, and loses to the
    line on a box at constant speed."""
    lin = {**QUICK, "structured": {"candidates": ["linear_trend"]}}
    damped = {**QUICK, "structured": {"candidates": ["damped_trend"], "trend_half_life": 4.0}}
    box = _uniform_box(64, 30)
    line = fit_and_rollout("mogaf", box, 12, lin, seed=0, rigid=True).poses
    slow = fit_and_rollout("mogaf", box, 12, damped, seed=0, rigid=True).poses
    centre = box[:, -1, :3].mean(0)
    share = damped_steps(12, 0.5 ** (1 / 4.0)) / np.arange(1, 13)
    ground = np.linalg.norm(slow[:, :, :3].mean(0) - centre, axis=-1)
    full = np.linalg.norm(line[:, :, :3].mean(0) - centre, axis=-1)
    np.testing.assert_allclose(ground, share * full, rtol=0.03)
    assert _pairwise_change(slow, box[:, -1]) < 1e-9

    weighed = {**QUICK, "structured": {"candidates": ["frozen", "linear_trend", "damped_trend"]}}
    decaying = _sliding_box(48, 40, lambda k: 0.05 * 0.9**k)
    steady = _sliding_box(48, 40, lambda k: np.full_like(k, 0.02))
    on_decay = fit_and_rollout("mogaf", decaying, 8, weighed, seed=0, rigid=True).info
    on_steady = fit_and_rollout("mogaf", steady, 8, weighed, seed=0, rigid=True).info
    assert on_decay["choice"] == "damped_trend", on_decay
    assert on_decay["backtest_epe_damped_trend"] < 0.8 * on_decay["backtest_epe_linear_trend"]
    assert on_steady["choice"] == "linear_trend", on_steady
    assert on_steady["backtest_epe_linear_trend"] < 0.1 * on_steady["backtest_epe_damped_trend"]


def test_drift_check_discounts_a_refit_that_learns_the_last_frames_artefact():
    """A box that slides uniformly, but whose last frames speed up (an end
    artefact of a reconstruction): the network backtested on the first frames
    saw none of it, the refit learns it. Their forecasts part far more than on
    the clean box; the drift raises the learned candidate's score, so it weighs
    less than without the check, and the weights are those of the combined
    scores."""
    traj = _uniform_box(48, 36)
    ramp = np.zeros(36)
    ramp[-8:] = 0.008 * np.arange(1, 9) ** 2  # the last 8 frames accelerate away along x
    obs = traj.copy()
    obs[:, :, 0] += ramp
    base = {**QUICK, "iterations": 200}
    on = fit_and_rollout("mogaf", obs, 12, base, seed=0, rigid=True).info
    off = fit_and_rollout("mogaf", obs, 12, {**base, "structured": {"drift_check": False}}, seed=0, rigid=True).info
    clean = fit_and_rollout("mogaf", traj, 12, base, seed=0, rigid=True).info
    assert "learned_refit_drift" not in off
    assert on["backtest_epe_learned"] == off["backtest_epe_learned"]  # the same backtested network
    assert clean["learned_refit_drift"] < 0.1 * on["learned_refit_drift"]
    assert on["backtest_weight_learned"] < off["backtest_weight_learned"]
    assert {c: on[f"backtest_weight_{c}"] for c in DEFAULT_CANDIDATES} == pytest.approx(_weights_of_the_scores(on))


def _braking(t: np.ndarray, start: np.ndarray, velocity: np.ndarray, deceleration: float) -> np.ndarray:
    """(len(t), 3) a point slowing uniformly along its velocity until it stops, then resting."""
    speed = float(np.linalg.norm(velocity))
    s = np.minimum(t, speed / deceleration)
    return start + np.outer(speed * s - 0.5 * deceleration * s**2, velocity / speed)


def test_braking_polynomial_equals_its_reference_and_stops_where_a_braking_point_stops():
    rng = np.random.default_rng(0)
    series = rng.normal(size=(9, 20)).cumsum(axis=1)
    for window in (1, 2, 3, 16, 40):
        np.testing.assert_allclose(
            braking_polynomial(series, window, 7), braking_polynomial_reference(series, window, 7), atol=1e-9
        )
    t, future = np.arange(20.0), np.arange(20.0, 40.0)
    start, velocity = np.array([1.0, -2.0, 0.5]), np.array([0.3, 0.1, -0.2])
    braking = _braking(t, start, velocity, 0.01)  # stops at step 37.4, within the forecast
    steady = start + np.outer(t, velocity)
    speeding = start + np.outer(t + 0.01 * t**2, velocity)
    rows = np.concatenate([braking.T, steady.T, speeding.T, np.full((3, 20), 4.0)])
    got = braking_polynomial(rows, 16, 20)
    np.testing.assert_allclose(got[:3], _braking(future, start, velocity, 0.01).T, atol=1e-9)
    np.testing.assert_allclose(got[3:6], (start + np.outer(future, velocity)).T, atol=1e-9)
    # speeding up: its last velocity, held, not more
    last_velocity = velocity * (1.0 + 0.02 * 19.0)
    np.testing.assert_allclose(got[6:9], (speeding[-1] + np.outer(future - 19.0, last_velocity)).T, atol=1e-9)
    np.testing.assert_allclose(got[9:], 4.0)
    with pytest.raises(ValueError, match="triples"):
        braking_polynomial(rows[:4], 16, 3)


def test_braking_candidate_brings_a_braking_box_to_rest_where_the_line_overshoots():
    """A box sliding to rest 8 steps after the last observed frame: the
    braking candidate is exact in the backtest, takes the weight, and the
    forecast stops where the box stops; the line carries it on."""
    rng = np.random.default_rng(1)
    pts = rng.uniform(-0.3, 0.3, size=(48, 3))
    q0 = quat.normalize(rng.normal(size=(48, 4)))
    path = _braking(np.arange(44.0), np.zeros(3), np.array([0.04, 0.02, 0.0]), 0.04 / 38)
    traj = rigid_motion(pts, q0, np.zeros(3), np.tile([1.0, 0.0, 0.0, 0.0], (44, 1)), path)
    obs, fut = traj[:, :30], traj[:, 30:]
    params = {**QUICK, "structured": {"candidates": ["frozen", "linear_trend", "braking"]}}
    res = fit_and_rollout("mogaf", obs, 14, params, seed=0, rigid=True)
    line = fit_and_rollout(
        "mogaf", obs, 14, {**QUICK, "structured": {"candidates": ["linear_trend"]}}, seed=0, rigid=True
    )
    assert res.info["choice"] == "braking" and res.info["backtest_weight_braking"] > 0.99
    np.testing.assert_allclose(res.poses[..., :3], fut[..., :3], atol=1e-4)
    assert np.abs(line.poses[:, -1, :3] - fut[:, -1, :3]).max() > 0.05


def test_constant_acceleration_carries_a_thrown_sphere_exactly_and_rigidly():
    """A thrown, spinning sphere: its accumulated spin is a line, so the turn
    is exact; its members' centroid (off the spin's centre) falls on a parabola
    plus a small circle, so the fall is close. The candidate alone trains no
    network, and the backtest of all four weighs it most."""
    traj = ballistic_sphere(64, 48)
    obs, fut = traj[:, :36], traj[:, 36:]
    only, info = _fit_structured(obs, {**QUICK, "structured": {"candidates": ["constant_acceleration"]}}, 0, True, 12)
    poses = only.rollout(12)
    assert np.all(quat.angle_between(poses[..., 3:], fut[..., 3:]) < 1e-7)
    cv = fit_and_rollout("constant_velocity", obs, 12).poses

    def epe(p):
        return np.linalg.norm(p[..., :3] - fut[..., :3], axis=-1).mean()

    assert epe(poses) < 0.1 * epe(cv)
    assert info["choice"] == "constant_acceleration" and info["iterations"] == 0
    assert "backtest_epe_learned" not in info
    every = {**QUICK, "structured": {"candidates": list(STRUCTURED_CANDIDATES)}}
    res = fit_and_rollout("mogaf", obs, 12, every, seed=0)
    assert res.info["choice"] == "constant_acceleration"
    assert res.info["backtest_weight_constant_acceleration"] > 0.5
    assert _pairwise_change(res.poses, obs[:, -1]) < 1e-9


# ---------------------------------------------------------------- coherence figure
def test_coherence_is_zero_for_rigid_and_still_and_not_for_drift():
    box = rigid_box(40, 30)
    obs, fut = box[:, :20, :3], box[:, 20:, :3]
    rng = np.random.default_rng(4)
    # group 1: a non-rigid group whose first 10 members never move, the rest do
    still_obs = np.repeat(rng.uniform(-1, 1, (10, 1, 3)), 20, axis=1) + rng.normal(0, 1e-4, (10, 20, 3))
    moving_obs = rigid_box(10, 20, seed=5)[..., :3] + 3.0
    still_fut = np.repeat(still_obs[:, -1:], 10, axis=1)
    moving_fut = np.repeat(moving_obs[:, -1:], 10, axis=1) + 0.1
    observed = np.concatenate([obs, still_obs, moving_obs])
    group_id = np.array([0] * 40 + [1] * 20)
    static, rigid = np.array([False, False]), np.array([True, False])
    good = coherence(observed, np.concatenate([fut, still_fut, moving_fut]), group_id, static, rigid)
    assert good["rigid_groups"] == 1 and good["rigid_distance_change"] < 1e-12
    assert good["still_gaussians"] == 10 and good["still_displacement"] == 0.0
    drift = fut + rng.normal(0, 0.01, fut.shape).cumsum(axis=1)
    bad = coherence(observed, np.concatenate([drift, still_fut + 0.02, moving_fut]), group_id, static, rigid)
    assert bad["rigid_distance_change"] > 1e-3 and bad["still_displacement"] == pytest.approx(np.sqrt(3) * 0.02)
    # members of static groups are not counted (no forecaster moves them)
    assert (
        coherence(observed, np.concatenate([fut, still_fut, moving_fut]), group_id, np.array([False, True]), rigid)[
            "still_gaussians"
        ]
        == 0
    )


def test_a_fast_spin_is_a_moving_body_for_the_forecaster_and_the_coherence_figure():
    """Spinning 1.2 rad a frame, every member's third differences exceed its
    reach, so each alone looks still; with no moving member left, the
    forecaster and the coherence figure both treat the whole group as the
    moving body (one test, mogaf.forecast.trajectory.rigid_group_still)."""
    angles = 1.2 * np.arange(30)
    radii = np.linspace(0.5, 1.0, 12)
    phase = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    a = angles[None, :] + phase[:, None]
    pos = np.stack([radii[:, None] * np.cos(a), radii[:, None] * np.sin(a), np.zeros_like(a)], -1)
    assert still_gaussians(pos, 3.0).all()  # the trap: alone, each member looks still
    assert not rigid_group_still(pos, 3.0).any()
    obs = np.concatenate([pos, np.tile([1.0, 0, 0, 0], (12, 30, 1))], -1)
    motion = GroupMotion(obs, True, 3.0)
    assert motion.moving.size == 12
    spun = motion.members(motion.constant_velocity_trajectory(5))
    figures = coherence(pos, spun[..., :3], np.zeros(12, int), np.array([False]), np.array([True]))
    assert figures["still_gaussians"] == 0 and figures["rigid_distance_change"] < 1e-9


def test_nonrigid_group_as_rigid_body_keeps_its_last_shape():
    """nonrigid_motion: rigid_body forecasts a group that is not rigid the way
    a rigid one is (the same poses, bit for bit): its members keep their last
    observed shape, where each Gaussian's own extrapolated jitter (the
    default) moves them apart."""
    box = add_noise(rigid_box(48, 24), pos_sigma=0.002, rot_sigma=0.0)
    as_body = {**QUICK, "structured": {"nonrigid_motion": "rigid_body"}}
    body = fit_and_rollout("mogaf", box, 8, as_body, seed=0, rigid=False)
    assert body.info["rigid"] is False and body.info["forecast_as"] == "rigid_body"
    np.testing.assert_array_equal(body.poses, fit_and_rollout("mogaf", box, 8, as_body, seed=0, rigid=True).poses)

    own = fit_and_rollout("mogaf", box, 8, PER_GAUSSIAN, seed=0, rigid=False)
    assert "forecast_as" not in own.info
    # mean pair change under 1e-12 over 1,128 pairs: every pair under about 1e-9
    assert _pairwise_change(body.poses, box[:, -1]) < 1e-12 < 1e-3 < _pairwise_change(own.poses, box[:, -1])


def _lid_on_still_body(frames: int) -> np.ndarray:
    """(72, frames, 7): a still box (48 Gaussians) and a lid (24) turning at a
    constant rate about a hinge along its back edge."""
    rng = np.random.default_rng(0)
    body = rng.uniform(-1, 1, (48, 3)) * [0.5, 0.3, 0.2]
    lid = rng.uniform(-1, 1, (24, 3)) * [0.5, 0.3, 0.02] + [0.0, 0.0, 0.25]
    q0 = quat.normalize(rng.normal(size=(72, 4)))
    still = np.repeat(np.array([[1.0, 0.0, 0.0, 0.0]]), frames, axis=0)
    turn = quat.from_axis_angle(np.broadcast_to([1.0, 0.0, 0.0], (frames, 3)), np.linspace(0.0, 1.2, frames))
    return np.concatenate(
        [
            rigid_motion(body, q0[:48], np.zeros(3), still, np.zeros((frames, 3))),
            rigid_motion(lid, q0[48:], np.array([0.0, -0.3, 0.23]), turn, np.zeros((frames, 3))),
        ]
    )


def test_rigid_parts_separate_a_lid_from_its_still_body():
    """trajectory.rigid_parts cuts a group into parts that each move as one
    rigid body: the still box is one part, the lid never shares one with it."""
    truth = _lid_on_still_body(32)
    labels = rigid_parts(add_noise(truth, pos_sigma=0.002, rot_sigma=0.0)[..., :3], 8, seed=0)
    assert len(set(labels[:48])) == 1 and labels[0] not in set(labels[48:])
    assert np.bincount(labels).min() >= 3
    # two exact rigid motions need two parts, however many are allowed
    labels = rigid_parts(truth[..., :3], 8, seed=0)
    assert len(set(labels)) == 2 and len(set(labels[:48])) == 1


def test_nonrigid_group_in_rigid_parts_keeps_each_part_rigid():
    """nonrigid_motion: rigid_parts forecasts each part as a rigid group: the
    still body stays within its noise, every part keeps its shape, and the
    lid's forecast is closer to its true turn than each Gaussian's own
    (the default) or the group's one rigid motion (rigid_body)."""
    truth = _lid_on_still_body(40)
    obs = add_noise(truth[:, :32], pos_sigma=0.002, rot_sigma=0.0)
    results = {
        mode: fit_and_rollout("mogaf", obs, 8, {**QUICK, "structured": {"nonrigid_motion": mode}}, seed=0, rigid=False)
        for mode in ("per_gaussian", "rigid_body", "rigid_parts")
    }
    parts = results["rigid_parts"]
    sizes = [int(n) for n in parts.info["part_members"].split()]
    assert parts.info["forecast_as"] == "rigid_parts" and sum(sizes) == 72 and parts.info["parts"] == len(sizes)
    assert len(parts.info["part_choices"].split()) == len(sizes)
    epe = {m: np.linalg.norm(r.poses[..., :3] - truth[:, 32:, :3], axis=-1) for m, r in results.items()}
    assert epe["rigid_parts"][:48].max() < 3 * 0.002 * np.sqrt(3)
    assert epe["rigid_parts"][48:].mean() < min(epe["per_gaussian"][48:].mean(), epe["rigid_body"][48:].mean())
    # within a part, the members that move (a rigid group's still ones keep their last pose) keep their shape
    labels = rigid_parts(obs[..., :3], 8, seed=0)
    moved = np.linalg.norm(parts.poses[:, -1, :3] - obs[:, -1, :3], axis=-1) > 0
    for p in range(labels.max() + 1):
        members = (labels == p) & moved
        if members.sum() >= 2:
            assert _pairwise_change(parts.poses[members], obs[members, -1]) < 1e-12
    again = fit_and_rollout("mogaf", obs, 8, {**QUICK, "structured": {"nonrigid_motion": "rigid_parts"}}, seed=0)
    np.testing.assert_array_equal(again.poses, parts.poses)


def test_a_group_its_rigid_parts_do_not_explain_is_forecast_per_gaussian():
    """200 points each at its own constant velocity leave about half their
    motion unexplained by 8 rigid parts: over parts_unexplained (0.45), the
    group is forecast per Gaussian, exactly as nonrigid_motion: per_gaussian
    would; the still box beside its hinged lid is explained (under 0.05) and
    cut into parts."""
    rng = np.random.default_rng(0)
    obs = np.empty((200, 30, 7))
    obs[..., :3] = rng.uniform(-1, 1, (200, 1, 3)) + np.arange(30)[None, :, None] * rng.normal(size=(200, 1, 3)) * 0.03
    obs[..., 3:] = quat.normalize(rng.normal(size=(200, 1, 4)))
    scattered = fit_and_rollout("mogaf", obs, 6, QUICK, seed=0, rigid=False)
    assert scattered.info["parts_unexplained"] > 0.5 and "parts" not in scattered.info
    np.testing.assert_array_equal(
        scattered.poses, fit_and_rollout("mogaf", obs, 6, PER_GAUSSIAN, seed=0, rigid=False).poses
    )
    hinge = fit_and_rollout("mogaf", _lid_on_still_body(32), 6, QUICK, seed=0, rigid=False)
    assert hinge.info["parts_unexplained"] < 0.05 and hinge.info["forecast_as"] == "rigid_parts"
