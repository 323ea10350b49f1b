"""The structured MoGaF forecast scaled by how well the reconstruction's last
observed image motion agrees with the 2D tracks (mogaf.forecast.track_agreement)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mogaf.errors import MogafError
from mogaf.forecast import quat
from mogaf.forecast.track_agreement import (
    TrackWindow,
    agreement_scale,
    body_scales,
    observed_track_window,
    sample_bilinear,
    scale_motion,
    track_motion_errors,
)
from mogaf.representation import GaussianSet, Model4D


def test_agreement_scale_is_the_least_squares_scale_of_a_noisy_velocity():
    assert agreement_scale(0.0, 2.0) == 1.0
    assert agreement_scale(2.0, 2.0) == pytest.approx(0.5)
    assert agreement_scale(1.0, 2.0) == pytest.approx(0.8)
    assert agreement_scale(3.0, 0.0) == 0.0  # a body that no longer moves in the tracks
    # Monte Carlo: scaling v + err by m^2 / (m^2 + e^2) minimises the mean squared error
    rng = np.random.default_rng(0)
    v = np.array([1.0, 0.5])
    err = rng.normal(size=(200000, 2)) * 0.8 / np.sqrt(2)
    est = v + err
    scales = np.linspace(0.0, 1.2, 121)
    mse = [np.mean(np.sum((s * est - v) ** 2, axis=1)) for s in scales]
    m2, e2 = v @ v, np.mean(np.sum(err**2, axis=1))
    assert scales[int(np.argmin(mse))] == pytest.approx(m2 / (m2 + e2), abs=0.01)


def test_body_scales_fall_back_to_the_job_then_to_none():
    figures = {-1: (1.0, 2.0, 12), 0: (2.0, 2.0, 9), 1: (9.0, 1.0, 2)}
    scales = body_scales(figures, min_tracks=5)
    assert scales[0] == pytest.approx(0.5)
    assert scales[1] == pytest.approx(0.8) == scales[-1]  # too few tracks: the job's figures
    assert body_scales({-1: (1.0, 2.0, 3), 0: (2.0, 2.0, 3)}, min_tracks=5) == {-1: 1.0, 0: 1.0}


def test_sample_bilinear_reads_pixel_centres_and_interpolates_between():
    image = np.arange(4 * 5 * 2, dtype=np.float64).reshape(4, 5, 2)
    centres = np.array([[0.5, 0.5], [4.5, 3.5], [2.5, 1.5]])
    np.testing.assert_allclose(sample_bilinear(image, centres), image[[0, 3, 1], [0, 4, 2]])
    mid = sample_bilinear(image, np.array([[1.0, 2.25]]))[0]  # halfway between columns 0, 1; 3/4 to row 2 from row 1
    expect = 0.25 * (0.5 * image[1, 0] + 0.5 * image[1, 1]) + 0.75 * (0.5 * image[2, 0] + 0.5 * image[2, 1])
    np.testing.assert_allclose(mid, expect)
    np.testing.assert_allclose(sample_bilinear(image, np.array([[-3.0, 9.0]]))[0], image[3, 0])  # clamped


def _turning_body(G: int = 12, T: int = 6, seed: int = 0):
    """Last poses (G, 7) and a forecast (G, T, 7) of one rigid body turning about z and drifting."""
    rng = np.random.default_rng(seed)
    last = np.zeros((G, 7))
    last[:, :3] = rng.normal(size=(G, 3)) * 0.3 + [1.0, 2.0, 3.0]
    q = rng.normal(size=(G, 4))
    last[:, 3:] = q / np.linalg.norm(q, axis=1, keepdims=True)
    centre = last[:, :3].mean(axis=0)
    poses = np.empty((G, T, 7))
    for t in range(T):
        turn = quat.from_axis_angle(np.array([0.0, 0.0, 1.0]), np.array([0.2 * (t + 1)]))[0]
        poses[:, t, :3] = centre + quat.rotate(turn, last[:, :3] - centre) + [0.05 * (t + 1), 0.0, 0.0]
        poses[:, t, 3:] = quat.mul(turn, last[:, 3:])
    return last, poses


def _distances(x: np.ndarray) -> np.ndarray:
    return np.linalg.norm(x[:, None] - x[None], axis=-1)


def _turn_z(angle: float) -> np.ndarray:
    return quat.from_axis_angle(np.array([0.0, 0.0, 1.0]), np.array([angle]))[0]


def test_a_rigid_body_is_scaled_as_one_and_stays_rigid():
    last, poses = _turning_body()
    bodies = np.zeros(len(last), np.int64)
    half = scale_motion(last, poses, bodies, {-1: 1.0, 0: 0.5})
    centre = last[:, :3].mean(0)
    for t in range(poses.shape[1]):
        # half the centroid's drift and half the turn, in the same direction
        turn = _turn_z(0.1 * (t + 1))
        expect = centre + quat.rotate(turn, last[:, :3] - centre) + [0.025 * (t + 1), 0.0, 0.0]
        np.testing.assert_allclose(half[:, t, :3], expect, atol=1e-9)
        np.testing.assert_allclose(np.abs(np.sum(half[:, t, 3:] * quat.mul(turn, last[:, 3:]), -1)), 1.0, atol=1e-12)
        np.testing.assert_allclose(_distances(half[:, t, :3]), _distances(last[:, :3]), atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(half[..., 3:], axis=-1), 1.0, atol=1e-12)
    # scale 1: the forecast as it is, bit for bit; scale 0: the last observed pose
    np.testing.assert_array_equal(scale_motion(last, poses, bodies, {-1: 1.0, 0: 1.0}), poses)
    still = scale_motion(last, poses, bodies, {-1: 1.0, 0: 0.0})
    np.testing.assert_allclose(still[..., :3], np.repeat(last[:, None, :3], poses.shape[1], 1), atol=1e-9)
    np.testing.assert_allclose(np.abs(np.sum(still[..., 3:] * last[:, None, 3:], -1)), 1.0, atol=1e-12)
    # members the forecast keeps still (their orientation renormalised) stay where they are
    kept = poses.copy()
    kept[:3] = last[:3, None]
    kept[:3, :, 3:] *= 1.0 + 1e-16
    out = scale_motion(last, kept, bodies, {-1: 1.0, 0: 0.5})
    np.testing.assert_array_equal(out[:3], kept[:3])
    np.testing.assert_allclose(_distances(out[3:, -1, :3]), _distances(last[3:, :3]), atol=1e-9)


def test_a_turn_beyond_half_a_revolution_is_scaled_along_its_path():
    last, poses = _turning_body(T=20)  # 0.2 rad per step: 4 rad at the end
    half = scale_motion(last, poses, np.zeros(len(last), np.int64), {-1: 1.0, 0: 0.5})
    expect = quat.mul(_turn_z(2.0), last[:, 3:])
    np.testing.assert_allclose(np.abs(np.sum(half[:, -1, 3:] * expect, -1)), 1.0, atol=1e-12)
    alone = scale_motion(last, poses, np.full(len(last), -1, np.int64), {-1: 0.5})
    np.testing.assert_allclose(np.abs(np.sum(alone[:, -1, 3:] * expect, -1)), 1.0, atol=1e-12)


def test_members_on_their_own_are_scaled_each_and_still_ones_stay():
    last, poses = _turning_body(G=6)
    poses[4:] = last[4:, None]  # the forecast keeps these still
    bodies = np.full(len(last), -1, np.int64)
    out = scale_motion(last, poses, bodies, {-1: 0.25})
    np.testing.assert_allclose(out[:4, :, :3] - last[:4, None, :3], 0.25 * (poses[:4, :, :3] - last[:4, None, :3]))
    for t in range(poses.shape[1]):  # a quarter of the turn, in the same direction
        expect = quat.mul(_turn_z(0.05 * (t + 1)), last[:4, 3:])
        np.testing.assert_allclose(np.abs(np.sum(out[:4, t, 3:] * expect, -1)), 1.0, atol=1e-12)
    np.testing.assert_array_equal(out[4:], poses[4:])


def _flat_model(velocity: np.ndarray, T: int = 5) -> Model4D:
    """A flat square of fg Gaussians 4 m in front of a camera at the origin,
    translating by `velocity` (world units) per step over T observed steps."""
    xs = np.linspace(-0.5, 0.5, 24)
    base = np.stack(np.meshgrid(xs, xs), -1).reshape(-1, 2)
    base = np.concatenate([base, np.full((base.shape[0], 1), 4.0)], 1)
    n = base.shape[0]
    traj = base[:, None] + np.arange(T)[None, :, None] * velocity
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    fg = GaussianSet(
        means=base.astype(np.float32),
        quats=quats.astype(np.float32),
        log_scales=np.full((n, 3), np.log(0.04), np.float32),
        opacity_logits=np.full(n, 4.0, np.float32),
        color_logits=np.zeros((n, 3), np.float32),
    )
    return Model4D(
        fg=fg,
        motion_coef_logits=np.zeros((n, 1), np.float32),
        rot6d=np.tile(np.array([1.0, 0, 0, 0, 1, 0], np.float32), (1, T, 1)),
        translations=np.zeros((1, T, 3), np.float32),
        timesteps=np.arange(T),
        trajectory_means=traj.astype(np.float32),
        trajectory_quats=np.repeat(quats[:, None], T, 1).astype(np.float32),
    )


def _window(
    true_velocity: np.ndarray, camera_shift: float = 0.0, steps: int = 3, start_focal: float = 64.0
) -> TrackWindow:
    """Tracks on the square at its end (a grid of pixels near the image's
    centre), where the true motion had them `steps` steps before; the start
    frame's camera may sit `camera_shift` aside, with another focal length."""
    from mogaf.camera import project

    K_end = np.array([[64.0, 0.0, 32.0], [0.0, 64.0, 32.0], [0.0, 0.0, 1.0]])
    K_start = np.array([[start_focal, 0.0, 31.0], [0.0, start_focal, 33.0], [0.0, 0.0, 1.0]])
    end, start = np.eye(4), np.eye(4)
    start[0, 3] = camera_shift
    gx, gy = np.meshgrid(np.arange(28.5, 37.0, 2.0), np.arange(28.5, 37.0, 2.0))
    xy_end = np.stack([gx.ravel(), gy.ravel()], 1)
    points_end = np.concatenate([(xy_end - 32.0) / 64.0 * 4.0, np.full((xy_end.shape[0], 1), 4.0)], 1)
    xy_start = project(points_end - steps * true_velocity, K_start, start)[0]
    return TrackWindow(1, 1 + steps, xy_start, xy_end, K_start, start, K_end, end, 64, 64)


@pytest.mark.parametrize("camera_shift", [0.0, 0.1])
def test_track_errors_measure_the_model_motion_against_the_tracks(camera_shift):
    v = np.array([0.02, -0.01, 0.0])
    members = np.arange(24 * 24)
    bodies = np.zeros(members.size, np.int64)
    right = track_motion_errors(_flat_model(v), members, bodies, _window(v, camera_shift))
    e, m, n = right[0]
    assert n == 25 and right[-1][2] == 25
    assert m == pytest.approx(64.0 * 3 * np.linalg.norm(v[:2]) / 4.0, rel=1e-4)
    assert e < 1e-3 and body_scales(right, 5)[0] > 0.999
    # the model moving twice as fast: its error is the tracks' motion, its scale 1/2
    double = track_motion_errors(_flat_model(2 * v), members, bodies, _window(v, camera_shift))
    assert double[0][0] == pytest.approx(double[0][1], rel=1e-3)
    assert body_scales(double, 5)[0] == pytest.approx(0.5, abs=1e-3)
    # a start frame with another focal length: motion in the end camera's pixels (to the
    # rendered point's sub-pixel offset, which no longer cancels)
    zoomed = track_motion_errors(_flat_model(v), members, bodies, _window(v, camera_shift, start_focal=56.0))
    assert zoomed[0][1] == pytest.approx(m, rel=0.03) and body_scales(zoomed, 5)[0] > 0.96
    # a still object seen from a moving camera: no motion of its own
    still = track_motion_errors(_flat_model(0 * v), members, bodies, _window(0 * v, camera_shift))
    assert still[0][1] < 0.02
    # tracks on what is not the job's (another group in front) do not count
    other = track_motion_errors(_flat_model(v), members[:10], bodies[:10], _window(v, camera_shift))
    assert other[-1][2] == 0


def test_each_body_is_judged_by_the_tracks_on_it():
    """The square's left half (body 0) moves as the tracks do, its right half
    (body 1) twice as fast: body 0 keeps its motion, body 1 gets about 1/2."""
    v = np.array([0.0, -0.01, 0.0])
    model = _flat_model(v)
    right_half = model.fg.means[:, 0] > 0.0
    model.trajectory_means[right_half] += (np.arange(5)[None, :, None] * v).astype(np.float32)
    members = np.arange(24 * 24)
    bodies = right_half.astype(np.int64)
    figures = track_motion_errors(model, members, bodies, _window(v))
    scales = body_scales(figures, 5)
    # columns at x 28.5, 30.5 on body 0, 34.5, 36.5 on body 1; 32.5 on the seam, on either
    assert figures[0][2] >= 10 and figures[1][2] >= 10 and figures[0][2] + figures[1][2] == 25
    assert scales[0] > 0.98 and scales[1] == pytest.approx(0.5, abs=0.01)
    assert figures[-1][2] == 25 and 0.5 < scales[-1] < scales[0]


def test_observed_track_window_reads_two_observed_frames_only(tmp_path):
    from mogaf.split import load_frames, read_split
    from support.forecast_scene import T_OBS, write_priors, write_scene

    scene_h5, split_h5 = write_scene(tmp_path, with_gt=True)
    split = read_split(split_h5)
    F = len(split.frame_ids["observed"])
    frames = load_frames(scene_h5, split, "observed")
    # track j at frame f sits at (f, j); track 2 is hidden at the last frame
    xy = np.stack(np.meshgrid(np.arange(F), np.arange(3), indexing="xy"), -1).astype(np.float64)
    visible = np.ones((3, F), np.uint8)
    visible[2, -1] = 0
    priors_h5 = write_priors(tmp_path / "priors.h5", scene_h5, split_h5, xy, visible)
    window = observed_track_window(priors_h5, scene_h5, split, 2)
    last = int(np.flatnonzero(frames.time_index == T_OBS - 1)[0])
    first = int(np.flatnonzero(frames.time_index == T_OBS - 3)[0])
    assert (window.step_start, window.step_end) == (T_OBS - 3, T_OBS - 1)
    np.testing.assert_array_equal(window.xy_end, [[last, 0], [last, 1]])
    np.testing.assert_array_equal(window.xy_start, [[first, 0], [first, 1]])
    np.testing.assert_array_equal(window.w2c_end, frames.w2c[last])
    # the same frames stored last first (h5py reads columns in increasing order only)
    backwards = write_priors(tmp_path / "backwards.h5", scene_h5, split_h5, xy, visible, reverse=True)
    again = observed_track_window(backwards, scene_h5, split, 2)
    np.testing.assert_array_equal(again.xy_start, window.xy_start)
    np.testing.assert_array_equal(again.xy_end, window.xy_end)
    assert observed_track_window(priors_h5, scene_h5, split, T_OBS) is None  # too few observed steps
    assert observed_track_window(write_priors(tmp_path / "none.h5", scene_h5, split_h5), scene_h5, split, 2) is None
    # priors of another split's frames are refused, naming the file
    other = dataclasses.replace(split, frame_ids={**split.frame_ids, "observed": split.frame_ids["observed"][:-1]})
    with pytest.raises(MogafError) as err:
        observed_track_window(priors_h5, scene_h5, other, 2)
    assert str(priors_h5) in str(err.value)
    # priors whose time steps miss an observed step: one line naming the file, not an IndexError
    shifted = write_priors(tmp_path / "shifted.h5", scene_h5, split_h5, xy, visible, step_shift=100)
    with pytest.raises(MogafError, match=f"{shifted}: has no frame at observed time step {T_OBS - 3}"):
        observed_track_window(shifted, scene_h5, split, 2)


def test_only_structured_mogaf_reads_tracks_and_it_needs_the_priors(tmp_path):
    from mogaf.forecast.registry import load_settings
    from mogaf.forecast.stage import job_track_window
    from mogaf.split import read_split
    from support.forecast_scene import write_priors, write_scene

    scene_h5, split_h5 = write_scene(tmp_path, with_gt=True)
    split = read_split(split_h5)
    F = len(split.frame_ids["observed"])
    priors_h5 = write_priors(tmp_path / "priors.h5", scene_h5, split_h5, np.zeros((4, F, 2)))
    mogaf = load_settings("mogaf", {})
    assert job_track_window(mogaf, priors_h5, scene_h5, split, "mogaf") is not None
    keep = load_settings("mogaf", {"structured": {"track_agreement": "keep"}})
    for settings, method in ((keep, "mogaf"), (load_settings("mogaf_paper", {}), "mogaf_paper")):
        assert job_track_window(settings, priors_h5, scene_h5, split, method) is None
    assert job_track_window(load_settings("constant_velocity", {}), None, None, split, "constant_velocity") is None
    with pytest.raises(MogafError, match="--priors-h5"):
        job_track_window(mogaf, None, scene_h5, split, "mogaf")


def test_track_settings_said_to_have_no_effect_are_not_read(tmp_path):
    """track_steps and min_tracks are inert under track_agreement: keep
    (inert_settings says so, and no tracks are read); under shrink,
    track_steps picks the window's first step."""
    from mogaf.forecast.params import inert_settings
    from mogaf.forecast.registry import load_settings
    from mogaf.forecast.stage import job_track_window
    from mogaf.split import read_split
    from support.forecast_scene import T_OBS, write_priors, write_scene

    def inert(structured):
        return {key for key, _ in inert_settings({"methods": ["mogaf"], "mogaf": {"structured": structured}})}

    changed = {"track_steps": 2, "min_tracks": 9}
    assert {"structured.track_steps", "structured.min_tracks"} <= inert({"track_agreement": "keep", **changed})
    assert not {"structured.track_steps", "structured.min_tracks"} & inert(changed)
    scene_h5, split_h5 = write_scene(tmp_path, with_gt=True)
    split = read_split(split_h5)
    priors_h5 = write_priors(tmp_path / "p.h5", scene_h5, split_h5, np.zeros((2, len(split.frame_ids["observed"]), 2)))
    keep = load_settings("mogaf", {"structured": {"track_agreement": "keep", **changed}})
    assert job_track_window(keep, priors_h5, scene_h5, split, "mogaf") is None
    shrink = load_settings("mogaf", {"structured": changed})
    assert job_track_window(shrink, priors_h5, scene_h5, split, "mogaf").step_start == T_OBS - 3


def test_a_forecast_job_halves_the_motion_the_tracks_see_at_half_speed():
    from mogaf.forecast.registry import load_settings
    from mogaf.forecast.stage import forecast_job

    v = np.array([0.02, -0.01, 0.0])
    model = _flat_model(v)
    members = np.arange(24 * 24)
    settings = load_settings("mogaf", {"iterations": 5, "structured": {"gate": False}})

    def job(window):
        return forecast_job(model, members, 4, settings, "mogaf", "0", 0, True, "cpu", None, window)

    fitted, _, _ = job(None)
    agreeing, info_agree, _ = job(_window(v, 0.1))
    halved, info, _ = job(_window(v / 2, 0.1))
    last = model.trajectory_means[:, -1].astype(np.float64)
    shift = (fitted[..., :3] - last[:, None]).mean(axis=0)
    assert np.linalg.norm(shift[-1]) > 0.05  # the fit goes on moving
    assert info_agree["track_count"] == 25 and info_agree["track_scale_min"] > 0.999
    np.testing.assert_allclose((agreeing[..., :3] - last[:, None]).mean(axis=0), shift, rtol=1e-3)
    assert info["track_scale_min"] == pytest.approx(0.5, abs=1e-3)
    np.testing.assert_allclose((halved[..., :3] - last[:, None]).mean(axis=0), 0.5 * shift, rtol=2e-3, atol=1e-9)
    np.testing.assert_allclose(_distances(halved[:, -1, :3])[:50, :50], _distances(last)[:50, :50], atol=1e-6)
