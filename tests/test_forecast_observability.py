"""Which directions the observed views constrain, and the structured MoGaF
forecast scaled down along the others (mogaf.forecast.observability)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mogaf.errors import MogafError
from mogaf.forecast.observability import (
    observed_view_centres,
    suppress_unobserved,
    unobserved_scaling,
    view_information,
)


def _rotation(seed: int) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_view_information_is_the_mean_squared_sine_with_the_rays():
    point = np.array([0.2, -0.1, 0.3])
    centres = np.random.default_rng(0).normal(size=(6, 3)) * 3.0
    info = view_information(point, centres)
    u = np.array([0.6, 0.0, 0.8])
    rays = point - centres
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    sine2 = 1.0 - (rays @ u) ** 2
    assert u @ info @ u == pytest.approx(sine2.mean(), rel=1e-12)
    np.testing.assert_allclose(info, info.T, atol=1e-15)
    # one camera: the ray itself is seen by no view, every direction across it fully
    lam, vec = np.linalg.eigh(view_information(point, centres[:1]))
    np.testing.assert_allclose(lam, [0.0, 1.0, 1.0], atol=1e-12)
    ray = (point - centres[0]) / np.linalg.norm(point - centres[0])
    assert abs(vec[:, 0] @ ray) == pytest.approx(1.0, abs=1e-12)
    # a camera at the point sees nothing
    np.testing.assert_array_equal(view_information(point, point[None]), np.zeros((3, 3)))


def test_unobserved_scaling_leaves_views_spread_around_the_scene_alone():
    # three orthogonal views: every direction has mean squared sine 2/3
    maps, scaled, smallest = unobserved_scaling(view_information(np.zeros(3), np.eye(3) * 4.0), 30.0)
    assert not scaled and smallest == 1.0
    np.testing.assert_array_equal(maps, np.eye(3))
    # one camera: the ray's direction scaled to zero, the others kept, symmetric
    ray = np.array([0.0, 0.0, 1.0])
    maps, scaled, smallest = unobserved_scaling(view_information(np.zeros(3), -3.0 * ray[None]), 30.0)
    assert scaled and smallest == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(maps, np.diag([1.0, 1.0, 0.0]), atol=1e-12)
    # views 10 degrees apart: along the mean ray, sin^2(5 deg) / sin^2(30 deg)
    a = np.radians(5.0)
    centres = -3.0 * np.array([[np.sin(a), 0.0, np.cos(a)], [-np.sin(a), 0.0, np.cos(a)]])
    maps, _, smallest = unobserved_scaling(view_information(np.zeros(3), centres), 30.0)
    assert maps[2, 2] == pytest.approx(np.sin(a) ** 2 / 0.25, rel=1e-9) == pytest.approx(smallest)
    assert maps[0, 0] == pytest.approx(1.0) and maps[1, 1] == pytest.approx(1.0)
    # no view of the point: nothing known, nothing scaled
    maps, scaled, _ = unobserved_scaling(view_information(np.zeros(3), np.zeros((1, 3))), 30.0)
    assert not scaled
    np.testing.assert_array_equal(maps, np.eye(3))
    # batched over points: each its own rays
    points = np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]])
    maps, scaled, _ = unobserved_scaling(view_information(points, -3.0 * ray[None]), 30.0)
    assert maps.shape == (2, 3, 3) and scaled.tolist() == [True, True]
    d = points[1] + 3.0 * ray
    d /= np.linalg.norm(d)
    np.testing.assert_allclose(maps[1] @ d, 0.0, atol=1e-12)


def _turning(last: np.ndarray, T: int, axis: int, shift: np.ndarray) -> np.ndarray:
    """(G, T, 3): the points turning about their centroid (about `axis`) and shifted, step by step."""
    centre = last.mean(axis=0)
    out = np.empty((last.shape[0], T, 3))
    for t, angle in enumerate(np.linspace(0.05, 0.25, T)):
        c, s = np.cos(angle), np.sin(angle)
        rot = np.roll(np.roll(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), axis, 0), axis, 1)
        out[:, t] = (last - centre) @ rot.T + centre + (t + 1) * shift
    return out


def test_bodies_stay_rigid_members_on_their_own_are_scaled_and_still_ones_stay():
    rng = np.random.default_rng(1)
    T = 5
    camera = np.array([[0.0, 0.0, -40.0]])
    a, b, c = rng.normal(size=(12, 3)), rng.normal(size=(9, 3)) + 3.0, rng.normal(size=(7, 3)) - 3.0
    last = np.concatenate([a, b, c])
    means = np.concatenate(
        [_turning(a, T, 0, np.array([0.1, 0.05, 0.3])), _turning(b, T, 1, np.array([-0.2, 0.0, 0.2])), c[:, None] + rng.normal(size=(7, T, 3))]
    )  # fmt: skip
    means[:3] = last[:3, None]  # members the forecast keeps still
    bodies = np.repeat([0, 1, -1], [12, 9, 7])
    out, figures = suppress_unobserved(last, means, bodies, camera, 30.0)
    np.testing.assert_array_equal(out[:3], means[:3])
    for members in (np.arange(3, 12), np.arange(12, 21)):
        for t in range(T):
            before = np.linalg.norm(means[members, t, None] - means[None, members, t], axis=-1)
            after = np.linalg.norm(out[members, t, None] - out[None, members, t], axis=-1)
            np.testing.assert_allclose(after, before, atol=1e-12)
        ray = last[members].mean(axis=0) - camera[0]
        ray /= np.linalg.norm(ray)
        np.testing.assert_allclose((out[members] - last[members, None]).mean(axis=0) @ ray, 0.0, atol=1e-12)
    rays = last[21:] - camera[0]
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    moved = out[21:] - last[21:, None]
    np.testing.assert_allclose(np.einsum("gti,gi->gt", moved, rays), 0.0, atol=1e-12)
    across = (means[21:] - last[21:, None]) - np.einsum("gti,gi->gt", means[21:] - last[21:, None], rays)[
        ..., None
    ] * rays[:, None]
    np.testing.assert_allclose(moved, across, atol=1e-12)
    assert figures["unobserved_scale_min"] == pytest.approx(0.0, abs=1e-12) and figures["view_spread_min"] < 1e-2
    # views all around: nothing scaled, the same values
    around = 40.0 * np.concatenate([np.eye(3), -np.eye(3)])
    same, figures = suppress_unobserved(last, means, bodies, around, 30.0)
    np.testing.assert_array_equal(same, means)
    assert figures["unobserved_scale_min"] == 1.0


def test_the_structured_forecaster_names_the_bodies_it_moves():
    """bodies(): a rigid group one body, rigid parts each theirs, per Gaussian -1."""
    from mogaf.forecast.registry import fit_and_rollout

    rng = np.random.default_rng(2)
    T = 24
    a, b = rng.normal(size=(10, 3)), rng.normal(size=(10, 3)) + 4.0
    pos = np.concatenate(
        [_turning(a, T, 2, np.array([0.02, 0.0, 0.0])), _turning(b, T, 0, np.array([0.0, -0.03, 0.01]))]
    )
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (20, T, 1))
    observed = np.concatenate([pos, quats], axis=-1)
    quick = {"iterations": 3}

    def bodies(structured, rigid):
        params = {**quick, "structured": {"gate": False, **structured}}
        return fit_and_rollout("mogaf", observed, 4, params, seed=0, rigid=rigid).bodies

    assert bodies({}, True).tolist() == [0] * 20
    assert bodies({"nonrigid_motion": "rigid_body"}, False).tolist() == [0] * 20
    assert bodies({"nonrigid_motion": "per_gaussian"}, False).tolist() == [-1] * 20
    parts = bodies({"nonrigid_motion": "rigid_parts", "rigid_parts": 2}, False)
    assert sorted(set(parts[:10])) == [parts[0]] and sorted(set(parts[10:])) == [parts[10]] and parts[0] != parts[10]
    assert fit_and_rollout("mogaf_paper", observed, 4, quick, seed=0).bodies is None


def test_observed_view_centres_read_the_last_observed_steps_only(tmp_path):
    from mogaf.camera import camera_centers
    from mogaf.split import load_frames, read_split
    from support.forecast_scene import T_OBS, write_scene

    scene_h5, split_h5 = write_scene(tmp_path, with_gt=True)
    split = read_split(split_h5)
    frames = load_frames(scene_h5, split, "observed")
    recent = np.asarray(frames.time_index) >= T_OBS - 2
    np.testing.assert_allclose(
        observed_view_centres(scene_h5, split, 2), camera_centers(np.asarray(frames.w2c)[recent]), atol=1e-12
    )
    assert observed_view_centres(scene_h5, split, 100).shape[0] == frames.num_frames
    # a split whose observed frames lie outside its observed steps (made for another scene) is refused
    other = dataclasses.replace(split, observed_timesteps=split.observed_timesteps[:-1])
    with pytest.raises(
        MogafError, match=r"frame \d+ of split role 'observed' is at time step \d+, outside the role's steps"
    ) as err:
        observed_view_centres(scene_h5, other, 2)
    assert str(scene_h5) in str(err.value)


def test_the_stage_scales_structured_mogaf_only_and_needs_the_scene(tmp_path, monkeypatch):
    """One camera looking along z: the structured forecast keeps no mean
    displacement along z in a rigid group and the same across; 'keep' and
    the paper's mode are left as fitted; without the scene it says so."""
    from mogaf.artefact import read_artefact
    from mogaf.forecast import stage as forecast_stage
    from mogaf.grouping.stage import write_groups
    from mogaf.representation import load_model
    from mogaf.split import read_split
    from support.forecast_scene import NONRIGID, RIGID, STATIC, groups_of, members, write_model, write_scene

    scene_h5, split_h5 = write_scene(tmp_path, with_gt=True)
    split = read_split(split_h5)
    model_h5 = write_model(tmp_path / "refined.h5", split.observed_timesteps)
    group_id = np.repeat([STATIC, RIGID, NONRIGID], members(0).size)
    groups_h5 = write_groups(tmp_path / "groups.h5", groups_of(group_id, static=[1, 0, 0], rigid=[1, 1, 0]))
    monkeypatch.setattr(forecast_stage, "observed_view_centres", lambda *a: np.array([[0.0, 0.0, -50.0]]))

    def run(name, structured, **kw):
        params = {"mogaf": {"iterations": 5, "structured": {"gate": False, "track_agreement": "keep", **structured}}}
        out = forecast_stage.run_forecast_group(
            str(model_h5), str(groups_h5), str(split_h5), str(tmp_path / name), params, job=str(RIGID), seed=0, **kw
        )
        art = read_artefact(out, "forecast_group")
        return np.asarray(art["means"], np.float64), art.attrs["info"]

    last = np.asarray(load_model(model_h5).trajectory_means[members(RIGID), -1], np.float64)
    kept, info_kept = run("keep.h5", {"unobserved_motion": "keep"}, method="mogaf", scene_h5=str(scene_h5))
    cut, info = run("cut.h5", {}, method="mogaf", scene_h5=str(scene_h5))
    assert "view_spread_min" not in info_kept and info["unobserved_scale_min"] == pytest.approx(0.0, abs=1e-6)
    ray = last.mean(axis=0) - np.array([0.0, 0.0, -50.0])
    ray /= np.linalg.norm(ray)
    shift_kept = (kept - last[:, None]).mean(axis=0)
    shift_cut = (cut - last[:, None]).mean(axis=0)
    assert np.abs(shift_kept @ ray).max() > 1e-2  # the fixture's rigid group moves along the ray
    np.testing.assert_allclose(shift_cut @ ray, 0.0, atol=1e-6)
    np.testing.assert_allclose(
        shift_cut - np.outer(shift_cut @ ray, ray), shift_kept - np.outer(shift_kept @ ray, ray), atol=1e-6
    )
    # the paper's mode and the baselines read no view: the same arrays with the scene as without
    for method in ("mogaf_paper", "constant_velocity"):
        with_scene, _ = run(f"{method}_s.h5", {}, method=method, scene_h5=str(scene_h5))
        np.testing.assert_array_equal(with_scene, run(f"{method}.h5", {}, method=method)[0])
    # views all around the group: the forecast as fitted, bit for bit
    around = 50.0 * np.concatenate([np.eye(3), -np.eye(3)])
    monkeypatch.setattr(forecast_stage, "observed_view_centres", lambda *a: around)
    np.testing.assert_array_equal(run("around.h5", {}, method="mogaf", scene_h5=str(scene_h5))[0], kept)
    with pytest.raises(MogafError, match="unobserved_motion: suppress reads the observed frames' camera poses"):
        run("none.h5", {}, method="mogaf")
    assert not (tmp_path / "none.h5").exists()


def test_view_settings_said_to_have_no_effect_change_no_forecast(tmp_path, monkeypatch):
    """view_window and observed_spread_deg are inert under unobserved_motion:
    keep (the same forecast, and inert_settings says so); under suppress,
    with views 10 degrees apart, the spread changes the forecast."""
    from mogaf.artefact import read_artefact
    from mogaf.forecast import stage as forecast_stage
    from mogaf.forecast.params import inert_settings
    from mogaf.grouping.stage import write_groups
    from mogaf.split import read_split
    from support.forecast_scene import NONRIGID, RIGID, STATIC, groups_of, members, write_model, write_scene

    scene_h5, split_h5 = write_scene(tmp_path, with_gt=True)
    model_h5 = write_model(tmp_path / "refined.h5", read_split(split_h5).observed_timesteps)
    group_id = np.repeat([STATIC, RIGID, NONRIGID], members(0).size)
    groups_h5 = write_groups(tmp_path / "groups.h5", groups_of(group_id, static=[1, 0, 0], rigid=[1, 1, 0]))
    a = np.radians(5.0)
    views = 50.0 * np.array([[np.sin(a), 0.0, -np.cos(a)], [-np.sin(a), 0.0, -np.cos(a)]])
    monkeypatch.setattr(forecast_stage, "observed_view_centres", lambda *args: views)

    def means(name, structured):
        params = {"mogaf": {"iterations": 5, "structured": {"gate": False, "track_agreement": "keep", **structured}}}
        out = forecast_stage.run_forecast_group(
            str(model_h5), str(groups_h5), str(split_h5), str(tmp_path / name), params,
            method="mogaf", job=str(NONRIGID), seed=0, scene_h5=str(scene_h5),
        )  # fmt: skip
        return np.asarray(read_artefact(out, "forecast_group")["means"])

    def inert(structured):
        return {key for key, _ in inert_settings({"methods": ["mogaf"], "mogaf": {"structured": structured}})}

    keep = {"unobserved_motion": "keep"}
    changed = {"view_window": 3, "observed_spread_deg": 20.0}
    assert inert({**keep, **changed}) - inert(keep) == {"structured.view_window", "structured.observed_spread_deg"}
    assert not inert(changed) & {"structured.view_window", "structured.observed_spread_deg"}
    np.testing.assert_array_equal(means("k1.h5", keep), means("k2.h5", {**keep, **changed}))
    assert np.abs(means("s1.h5", {}) - means("s2.h5", {"observed_spread_deg": 20.0})).max() > 1e-6
    assert np.abs(means("s1.h5", {}) - means("k1.h5", keep)).max() > 1e-6
