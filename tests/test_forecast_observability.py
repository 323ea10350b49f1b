"""Which directions the observed views constrain, and the structured MoGaF
forecast scaled down along the others (mogaf.forecast.observability)."""

from __future__ import annotations

import numpy as np
import pytest

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
    centres = np.eye(3) * 4.0
    assert unobserved_scaling(view_information(np.zeros(3), centres), 30.0) is None
    # one camera: the ray's direction scaled to zero, the others kept, symmetric
    ray = np.array([0.0, 0.0, 1.0])
    scaling = unobserved_scaling(view_information(np.zeros(3), -3.0 * ray[None]), 30.0)
    np.testing.assert_allclose(scaling, np.diag([1.0, 1.0, 0.0]), atol=1e-12)
    # views 10 degrees apart: along the mean ray, sin^2(5 deg) / sin^2(30 deg)
    a = np.radians(5.0)
    centres = -3.0 * np.array([[np.sin(a), 0.0, np.cos(a)], [-np.sin(a), 0.0, np.cos(a)]])
    scaling = unobserved_scaling(view_information(np.zeros(3), centres), 30.0)
    assert scaling[2, 2] == pytest.approx(np.sin(a) ** 2 / 0.25, rel=1e-9)
    assert scaling[0, 0] == pytest.approx(1.0) and scaling[1, 1] == pytest.approx(1.0)


def test_rigid_groups_stay_rigid_and_still_members_still():
    rng = np.random.default_rng(1)
    last = rng.normal(size=(40, 3))
    T = 5
    angles = np.linspace(0.05, 0.25, T)
    shift = np.outer(np.arange(1, T + 1), [0.1, 0.05, 0.3])
    centre = last.mean(axis=0)
    means = np.empty((40, T, 3))
    for t, a in enumerate(angles):
        c, s = np.cos(a), np.sin(a)
        rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        means[:, t] = (last - centre) @ rot.T + centre + shift[t]
    means[:5] = last[:5, None]  # members the forecast keeps still
    scaling = np.diag([1.0, 1.0, 0.0])
    out = suppress_unobserved(last, means, scaling, rigid=True)
    np.testing.assert_array_equal(out[:5], means[:5])
    moving = out[5:]
    for t in range(T):
        before = np.linalg.norm(means[5:, t, None] - means[None, 5:, t], axis=-1)
        after = np.linalg.norm(moving[:, t, None] - moving[None, :, t], axis=-1)
        np.testing.assert_allclose(after, before, atol=1e-12)
    # the moving members' mean displacement keeps no component along z
    mean_disp = (moving - last[5:, None]).mean(axis=0)
    np.testing.assert_allclose(mean_disp[:, 2], 0.0, atol=1e-12)
    np.testing.assert_allclose(mean_disp[:, :2], (means[5:] - last[5:, None]).mean(axis=0)[:, :2], atol=1e-12)


def test_nonrigid_members_are_scaled_one_by_one():
    rng = np.random.default_rng(3)
    last = rng.normal(size=(10, 3))
    means = last[:, None] + rng.normal(size=(10, 4, 3))
    R = _rotation(4)
    scaling = R @ np.diag([1.0, 0.5, 0.0]) @ R.T
    out = suppress_unobserved(last, means, scaling, rigid=False)
    np.testing.assert_allclose(out - last[:, None], (means - last[:, None]) @ scaling.T, atol=1e-12)
    # the identity changes nothing
    np.testing.assert_allclose(suppress_unobserved(last, means, np.eye(3), rigid=False), means, atol=1e-15)


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


def test_the_stage_scales_structured_mogaf_only_and_needs_the_scene(tmp_path, monkeypatch):
    """One camera looking along z: the structured forecast keeps no mean
    displacement along z in a rigid group and the same across; 'keep' and
    the paper's mode are left as fitted; without the scene it says so."""
    from mogaf.artefact import read_artefact
    from mogaf.errors import MogafError
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
        params = {"mogaf": {"iterations": 5, "structured": {"gate": False, **structured}}}
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
    paper, _ = run("paper.h5", {}, method="mogaf_paper")  # the paper's mode reads no view
    assert paper.shape == kept.shape
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
        params = {"mogaf": {"iterations": 5, "structured": {"gate": False, **structured}}}
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
