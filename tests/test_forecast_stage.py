"""Forecast stage (mogaf.forecast.stage): job lists, group jobs, the merge, quick EPE.

Inputs are written with the library's own writers (support.forecast_scene):
a scene.h5 of tiny blank frames (8 time steps, ratio 0.5: steps 0-3
observed, 4-7 forecast) with ground-truth 3D points riding on the rigid
group, its split.h5, a refine-stage model whose 30 foreground Gaussians have
known trajectories, and (here) a groups.h5 with three groups:
  0 static (10 Gaussians, never move)
  1 rigid dynamic (10 Gaussians, one common constant velocity)
  2 non-rigid dynamic (10 Gaussians, each its own constant velocity and a
    fixed random orientation)
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest

from mogaf.artefact import read_artefact
from mogaf.errors import MogafError
from mogaf.evaluate import DEFAULT_PARAMS as EVAL_PARAMS
from mogaf.evaluate.tracking import tracking_section
from mogaf.forecast.params import INLINE_METHODS
from mogaf.forecast.stage import (
    forecast_jobs,
    method_jobs,
    run_forecast_group,
    run_forecast_merge,
)
from mogaf.grouping.stage import write_groups
from mogaf.representation import load_model
from mogaf.split import read_split
from support.forecast_scene import (
    N_PER,
    NONRIGID,
    RATIO,
    RIGID,
    RIGID_VELOCITY,
    STATIC,
    T_OBS,
    N,
    T,
    members,
    world,
    write_model,
    write_priors,
    write_scene,
)
from support.forecast_scene import (
    groups_of as _groups,
)

# gate off: the learned candidate runs, so the seed matters (the gate may pick one that trains nothing)
MOGAF_FAST = {"mogaf": {"iterations": 5, "structured": {"gate": False}}}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("fc")
    scene_h5, split_h5 = write_scene(folder, with_gt=True)
    split = read_split(split_h5)
    assert split.observed_timesteps.tolist() == list(range(T_OBS))
    assert split.forecast_timesteps.tolist() == list(range(T_OBS, T))
    model_h5 = write_model(folder / "refined.h5", split.observed_timesteps)
    group_id = np.repeat([STATIC, RIGID, NONRIGID], N_PER)
    groups_h5 = write_groups(folder / "groups.h5", _groups(group_id, static=[1, 0, 0], rigid=[1, 1, 0]))
    priors_h5 = write_priors(folder / "priors.h5", scene_h5, split_h5)  # no tracks: every forecast as fitted
    return {
        "folder": folder,
        "scene": scene_h5,
        "split": split_h5,
        "model": model_h5,
        "groups": groups_h5,
        "priors": priors_h5,
    }


@pytest.fixture(scope="module")
def mogaf_parts(inputs, tmp_path_factory) -> list[Path]:
    out = tmp_path_factory.mktemp("parts")
    return [
        run_forecast_group(
            str(inputs["model"]),
            str(inputs["groups"]),
            str(inputs["split"]),
            str(out / f"group{j}.h5"),
            MOGAF_FAST,
            method="mogaf",
            job=j,
            seed=7,
            scene_h5=str(inputs["scene"]),
            priors_h5=str(inputs["priors"]),
        )
        for j in forecast_jobs(inputs["groups"], groupwise=True)
    ]


def _merge(inputs, out: Path, parts: list, method: str, params=None, seed: int = 0) -> Path:
    return run_forecast_merge(
        str(inputs["model"]),
        str(inputs["groups"]),
        str(inputs["split"]),
        [str(p) for p in parts],
        str(out),
        params or {},
        method=method,
        seed=seed,
        scene_h5=str(inputs["scene"]),
        priors_h5=str(inputs["priors"]),
    )


def _arrays(path: Path) -> dict[str, np.ndarray]:
    out = {}
    with h5py.File(path, "r") as fh:
        fh.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


# ------------------------------------------------------------------ job lists
def test_forecast_jobs_lists_dynamic_groups(inputs, tmp_path):
    assert forecast_jobs(inputs["groups"], groupwise=True) == [str(RIGID), str(NONRIGID)]
    assert forecast_jobs(inputs["groups"], groupwise=False) == ["all"]
    # an empty dynamic group gets no job
    gid = np.repeat([0, 1, 3], N_PER)
    g = write_groups(tmp_path / "holes.h5", _groups(gid, static=[1, 0, 0, 0], rigid=[1, 1, 0, 0]))
    assert forecast_jobs(g, groupwise=True) == ["1", "3"]
    # an all-static grouping has nothing to forecast
    still = write_groups(
        tmp_path / "static.h5", _groups(np.repeat([0, 1, 2], N_PER), static=[1, 1, 1], rigid=[1, 1, 1])
    )
    assert forecast_jobs(still, groupwise=True) == []
    assert forecast_jobs(still, groupwise=False) == []


def test_method_jobs(inputs):
    assert set(INLINE_METHODS) == {"constant_velocity", "frozen"}
    per_group = forecast_jobs(inputs["groups"], groupwise=True)
    joint = forecast_jobs(inputs["groups"], groupwise=False)
    for m in INLINE_METHODS:
        assert method_jobs(m, per_group) == []
        assert method_jobs(m, joint) == []
    for m in ("mogaf", "gcn", "ode"):
        assert method_jobs(m, per_group) == [str(RIGID), str(NONRIGID)]
        assert method_jobs(m, joint) == ["all"]
        # forecast.jobs: per_method: the merge job runs them all
        assert method_jobs(m, per_group, "per_method") == []
    with pytest.raises(MogafError, match="forecast.jobs must be one of per_group, per_method, got 'per_gaussian'"):
        method_jobs("mogaf", per_group, "per_gaussian")


# ------------------------------------------------------------------ group jobs
def test_group_job_constant_velocity(inputs, tmp_path):
    out = run_forecast_group(
        str(inputs["model"]),
        str(inputs["groups"]),
        str(inputs["split"]),
        str(tmp_path / "g.h5"),
        {},
        method="constant_velocity",
        job=str(NONRIGID),
        seed=0,
    )
    art = read_artefact(out, "forecast_group")
    assert art["members"].tolist() == members(NONRIGID).tolist()
    assert art["means"].shape == (N_PER, T - T_OBS, 3) and art["quats"].shape == (N_PER, T - T_OBS, 4)
    assert art.attrs["method"] == "constant_velocity" and art.attrs["job"] == str(NONRIGID)
    assert art.attrs["num_gaussians"] == N_PER
    pos, quats, _ = world()
    np.testing.assert_allclose(art["means"], pos[members(NONRIGID), T_OBS:], atol=1e-5)
    np.testing.assert_allclose(np.abs(np.sum(art["quats"] * quats[members(NONRIGID), None], -1)), 1.0, atol=1e-5)


def test_group_job_mogaf_all(inputs, tmp_path):
    out = run_forecast_group(
        str(inputs["model"]),
        str(inputs["groups"]),
        str(inputs["split"]),
        str(tmp_path / "all.h5"),
        MOGAF_FAST,
        method="mogaf",
        job="all",
        seed=0,
        device="auto",
        scene_h5=str(inputs["scene"]),
        priors_h5=str(inputs["priors"]),
    )
    art = read_artefact(out, "forecast_group")
    assert art.attrs["info"]["device"] in ("cpu", "cuda")  # the device the network ran on, recorded
    dynamic = np.concatenate([members(RIGID), members(NONRIGID)])
    assert art["members"].tolist() == dynamic.tolist()
    assert art["means"].shape == (2 * N_PER, T - T_OBS, 3) and art["quats"].shape == (2 * N_PER, T - T_OBS, 4)
    assert np.all(np.isfinite(art["means"]))
    np.testing.assert_allclose(np.linalg.norm(art["quats"], axis=-1), 1.0, atol=1e-4)


def test_group_job_refuses_static_and_bad_jobs(inputs, tmp_path):
    args = (str(inputs["model"]), str(inputs["groups"]), str(inputs["split"]), str(tmp_path / "x.h5"), MOGAF_FAST)
    with pytest.raises(MogafError, match="static") as err:
        run_forecast_group(*args, method="mogaf", job=str(STATIC), seed=0)
    assert str(inputs["groups"]) in str(err.value)
    with pytest.raises(MogafError, match="no group 7") as err:
        run_forecast_group(*args, method="mogaf", job="7", seed=0)
    assert str(inputs["groups"]) in str(err.value)
    with pytest.raises(MogafError, match="neither a group id"):
        run_forecast_group(*args, method="mogaf", job="groupA", seed=0)
    with pytest.raises(MogafError, match="unknown method"):
        run_forecast_group(*args, method="nosuch", job=str(RIGID), seed=0)
    assert not (tmp_path / "x.h5").exists()


def test_group_job_checks_model_against_split(inputs, tmp_path):
    short = write_model(tmp_path / "short.h5", np.arange(T_OBS - 1))
    with pytest.raises(MogafError, match="split observes"):
        run_forecast_group(
            str(short),
            str(inputs["groups"]),
            str(inputs["split"]),
            str(tmp_path / "x.h5"),
            {},
            method="constant_velocity",
            job=str(RIGID),
            seed=0,
        )
    # the groups of another model: refused by the stage (mogaf.stages), once, before the job runs
    from mogaf.stages import forecast_group

    gid = np.repeat([0, 1], N_PER)
    small = write_groups(tmp_path / "small.h5", _groups(gid, static=[1, 0], rigid=[1, 1]))
    with pytest.raises(MogafError, match=f"assigns groups to {2 * N_PER} Gaussians, but the model .* has {N}"):
        forecast_group(
            str(inputs["model"]),
            str(small),
            str(inputs["split"]),
            str(tmp_path / "x.h5"),
            {},
            method="constant_velocity",
            group="1",
            seed=0,
        )


@pytest.mark.parametrize("method", ["mogaf", "gcn"])
def test_a_job_loads_and_checks_its_settings_once(inputs, tmp_path, monkeypatch, method):
    """Each setting's bounds (settings.check) and MoGaF's structured part and
    relations (params.load_mogaf) are checked once per job, where it starts."""
    import mogaf.forecast.base
    import mogaf.forecast.mogaf_settings
    import mogaf.forecast.params

    calls = {"check": 0, "load_mogaf": 0}

    def counted(name, fn):
        def wrapper(*args, **kwargs):
            calls[name] += 1
            return fn(*args, **kwargs)

        return wrapper

    monkeypatch.setattr(mogaf.forecast.base, "check", counted("check", mogaf.forecast.base.check))
    load_mogaf = counted("load_mogaf", mogaf.forecast.params.load_mogaf)
    monkeypatch.setattr(mogaf.forecast.params, "load_mogaf", load_mogaf)
    monkeypatch.setattr(mogaf.forecast.mogaf_settings, "load_mogaf", load_mogaf)
    params = {"mogaf": {"iterations": 5}, "gcn": {"n_nodes": 4, "num_stage": 1, "linear_size": 8, "epochs": 1}}
    run_forecast_group(
        str(inputs["model"]),
        str(inputs["groups"]),
        str(inputs["split"]),
        str(tmp_path / "x.h5"),
        params,
        method=method,
        job=str(RIGID),
        seed=0,
        scene_h5=str(inputs["scene"]),
        priors_h5=str(inputs["priors"]),
    )
    assert calls == {"check": 1, "load_mogaf": 1 if method == "mogaf" else 0}


# ------------------------------------------------------------------ merge
def test_merge_inline_constant_velocity(inputs, tmp_path):
    out = _merge(inputs, tmp_path / "constant_velocity.h5", [], "constant_velocity", {"groupwise": True})
    art = read_artefact(out, "forecast")
    pos, quats, _ = world()
    means, q = np.asarray(art["means"]), np.asarray(art["quats"])
    assert art["timesteps"].tolist() == list(range(T_OBS, T))
    assert means.shape == (N, T - T_OBS, 3) and q.shape == (N, T - T_OBS, 4)
    assert art["group_id"].tolist() == np.repeat([0, 1, 2], N_PER).tolist()
    # static: exactly the last observed pose (bit for bit) at every step
    model = load_model(inputs["model"])
    s = members(STATIC)
    for i in range(T - T_OBS):
        np.testing.assert_array_equal(means[s, i], model.trajectory_means[s, -1])
        np.testing.assert_array_equal(q[s, i], model.trajectory_quats[s, -1])
    # linear movers continue linearly: x(t) = x(T_obs - 1) + v (t - T_obs + 1)
    dyn = np.concatenate([members(RIGID), members(NONRIGID)])
    np.testing.assert_allclose(means[dyn], pos[dyn, T_OBS:], atol=1e-5)
    np.testing.assert_allclose(
        means[members(RIGID), -1] - means[members(RIGID), 0], np.tile(3 * RIGID_VELOCITY, (N_PER, 1)), atol=1e-5
    )
    np.testing.assert_allclose(np.abs(np.sum(q[dyn] * quats[dyn, None], -1)), 1.0, atol=1e-5)
    assert art.attrs["method"] == "constant_velocity" and art.attrs["groupwise"] is True
    assert art.attrs["params"] == {}
    assert set(art.attrs["flags"]) == {str(RIGID), str(NONRIGID)}


def test_merge_inline_not_groupwise_and_frozen(inputs, tmp_path):
    art = read_artefact(_merge(inputs, tmp_path / "cv.h5", [], "constant_velocity", {"groupwise": False}), "forecast")
    assert set(art.attrs["flags"]) == {"all"} and art.attrs["groupwise"] is False
    pos, _, _ = world()
    np.testing.assert_allclose(art["means"][N_PER:], pos[N_PER:, T_OBS:], atol=1e-5)
    frozen = read_artefact(_merge(inputs, tmp_path / "frozen.h5", [], "frozen"), "forecast")
    last = load_model(inputs["model"]).trajectory_means[:, -1]
    np.testing.assert_allclose(frozen["means"], np.repeat(last[:, None], T - T_OBS, axis=1), atol=1e-6)


def test_merge_inline_refuses_parts(inputs, tmp_path):
    part = run_forecast_group(
        str(inputs["model"]),
        str(inputs["groups"]),
        str(inputs["split"]),
        str(tmp_path / "g1.h5"),
        {},
        method="constant_velocity",
        job=str(RIGID),
        seed=0,
    )
    with pytest.raises(MogafError, match="takes no group files"):
        _merge(inputs, tmp_path / "out.h5", [part], "constant_velocity")
    assert not (tmp_path / "out.h5").exists()


def test_merge_trained_method_covers_every_dynamic_gaussian(inputs, mogaf_parts, tmp_path):
    out = _merge(inputs, tmp_path / "mogaf.h5", mogaf_parts, "mogaf", {"groupwise": True, **MOGAF_FAST}, seed=7)
    art = read_artefact(out, "forecast")
    assert art.attrs["method"] == "mogaf" and art.attrs["num_groups_trained"] == 2
    assert art.attrs["params"]["iterations"] == 5
    assert set(art.attrs["flags"]) == {str(RIGID), str(NONRIGID)}
    means = np.asarray(art["means"])
    model = load_model(inputs["model"])
    for p in mogaf_parts:
        part = read_artefact(p, "forecast_group")
        np.testing.assert_array_equal(means[part["members"]], part["means"])
        np.testing.assert_array_equal(np.asarray(art["quats"])[part["members"]], part["quats"])
    s = members(STATIC)
    np.testing.assert_array_equal(means[s], np.repeat(model.trajectory_means[s, -1:], T - T_OBS, axis=1))
    covered = np.concatenate([read_artefact(p, "forecast_group")["members"] for p in mogaf_parts])
    assert sorted(covered.tolist()) == list(range(N_PER, N))


def test_merge_per_method_is_the_group_jobs_forecast(inputs, mogaf_parts, tmp_path, monkeypatch):
    """forecast.jobs: per_method trains every group inside the merge job: the
    same poses, bit for bit, as the group jobs merged (their seeds and
    settings), each group on the job's thread count whatever the process's,
    and it takes no group files."""
    import torch

    from mogaf.forecast import stage as forecast_stage

    params = {"groupwise": True, **MOGAF_FAST}
    per_group = read_artefact(_merge(inputs, tmp_path / "pg.h5", mogaf_parts, "mogaf", params, seed=7), "forecast")
    threads_seen = []
    fit = forecast_stage.fit_and_rollout

    def recording(*args, **kwargs):
        threads_seen.append(torch.get_num_threads())
        return fit(*args, **kwargs)

    monkeypatch.setattr(forecast_stage, "fit_and_rollout", recording)
    before = torch.get_num_threads()
    torch.set_num_threads(3)
    try:
        out = run_forecast_merge(
            str(inputs["model"]),
            str(inputs["groups"]),
            str(inputs["split"]),
            [],
            str(tmp_path / "pm.h5"),
            {**params, "jobs": "per_method"},
            method="mogaf",
            seed=7,
            scene_h5=str(inputs["scene"]),
            priors_h5=str(inputs["priors"]),
            threads=1,
        )
        assert torch.get_num_threads() == 3  # restored
    finally:
        torch.set_num_threads(before)
    assert threads_seen == [1, 1]
    per_method = read_artefact(out, "forecast")
    for key in ("means", "quats", "group_id", "timesteps"):
        np.testing.assert_array_equal(per_method[key], per_group[key])
    assert per_method.attrs["job_layout"] == "per_method" and per_group.attrs["job_layout"] == "per_group"
    assert per_method.attrs["num_groups_trained"] == 2
    assert set(per_method.attrs["flags"]) == {str(RIGID), str(NONRIGID)}
    with pytest.raises(MogafError, match=r"computed in the merge job \(per_method\), it takes no group files"):
        _merge(inputs, tmp_path / "x.h5", mogaf_parts, "mogaf", {**params, "jobs": "per_method"}, seed=7)
    assert not (tmp_path / "x.h5").exists()


def test_merge_refuses_missing_overlapping_and_foreign_parts(inputs, mogaf_parts, tmp_path):
    with pytest.raises(MogafError, match=f"{N_PER} dynamic Gaussians are covered by no forecast job"):
        _merge(inputs, tmp_path / "a.h5", mogaf_parts[:1], "mogaf", MOGAF_FAST)
    with pytest.raises(MogafError, match="covered by no forecast job"):
        _merge(inputs, tmp_path / "b.h5", [], "mogaf", MOGAF_FAST)
    with pytest.raises(MogafError, match="overlaps"):
        _merge(inputs, tmp_path / "c.h5", [mogaf_parts[0], mogaf_parts[0]], "mogaf", MOGAF_FAST)
    whole = run_forecast_group(
        str(inputs["model"]),
        str(inputs["groups"]),
        str(inputs["split"]),
        str(tmp_path / "all.h5"),
        MOGAF_FAST,
        method="mogaf",
        job="all",
        seed=7,
        scene_h5=str(inputs["scene"]),
        priors_h5=str(inputs["priors"]),
    )
    with pytest.raises(MogafError, match="overlaps"):
        _merge(inputs, tmp_path / "d.h5", [mogaf_parts[0], whole], "mogaf", MOGAF_FAST)
    with pytest.raises(MogafError, match="expected 'gcn'"):
        _merge(inputs, tmp_path / "e.h5", mogaf_parts, "gcn", {})
    for name in "abcde":
        assert not (tmp_path / f"{name}.h5").exists()


def test_evaluation_quick_epe_measures_the_error(inputs, tmp_path):
    """The quick 3D checks live in evaluation, the only stage that reads the scene's future."""
    model = load_model(inputs["model"])
    split = read_split(inputs["split"])
    pos, quats, _ = world()
    q = np.repeat(quats[:, None], T - T_OBS, axis=1)
    scene = str(inputs["scene"])
    exact = tracking_section(model, {"means": pos[:, T_OBS:], "quats": q}, scene, split, EVAL_PARAMS)[1]
    assert exact["epe_3d_quick"] == pytest.approx(0.0, abs=1e-5)
    assert exact == {"epe_3d_quick": exact["epe_3d_quick"], "still_points": 0}  # the GT points all move
    shifted = pos[:, T_OBS:] + np.array([0.0, 0.3, 0.0])
    assert tracking_section(model, {"means": shifted, "quats": q}, scene, split, EVAL_PARAMS)[1][
        "epe_3d_quick"
    ] == pytest.approx(0.3, abs=1e-5)
    # frozen leaves the GT points riding the rigid group behind by 1..4 steps of its velocity
    frozen = read_artefact(_merge(inputs, tmp_path / "frozen.h5", [], "frozen"), "forecast")
    fc = {"means": np.asarray(frozen["means"]), "quats": np.asarray(frozen["quats"])}
    expected = np.linalg.norm(RIGID_VELOCITY) * np.mean(np.arange(1, T - T_OBS + 1))
    assert tracking_section(model, fc, scene, split, EVAL_PARAMS)[1]["epe_3d_quick"] == pytest.approx(
        expected, rel=1e-3
    )
    assert "epe_3d_quick" not in frozen.attrs
    scene_h5, _ = write_scene(tmp_path / "nogt", with_gt=False)
    assert tracking_section(model, fc, str(scene_h5), split, EVAL_PARAMS) == (None, None)
    # points resting on the static group: frozen leaves them, a shifted forecast moves them by its shift
    still_h5, _ = write_scene(tmp_path / "still", with_gt=True, still_gt=True)
    quick = tracking_section(model, fc, str(still_h5), split, EVAL_PARAMS)[1]
    assert quick["still_points"] == N_PER and quick["still_points_displacement"] == pytest.approx(0.0, abs=1e-6)
    moved = {"means": np.asarray(frozen["means"]) + np.array([0.0, 0.3, 0.4]), "quats": fc["quats"]}
    quick = tracking_section(model, moved, str(still_h5), split, EVAL_PARAMS)[1]
    assert quick["still_points_displacement"] == pytest.approx(0.5, abs=1e-6)


def test_2d_tracking_scores_only_the_steps_the_training_camera_has_a_frame_of(inputs, tmp_path):
    """A forecast step the training camera has no frame of is left out of the
    2D metrics, not scored as a track predicted invisible at pixel (0, 0). In
    this scene every step looks alike to the static training camera (the
    same points in view), so leaving one out changes no metric; scoring it
    would lower AJ and occlusion accuracy (0.7 -> 0.525)."""
    model = load_model(inputs["model"])
    pos, quats, _ = world()
    fc = {"means": pos[:, T_OBS:], "quats": np.repeat(quats[:, None], T - T_OBS, axis=1)}
    full_h5, split_h5 = write_scene(tmp_path / "full", with_gt=True, tracks2d=True)
    full = tracking_section(model, fc, str(full_h5), read_split(split_h5), EVAL_PARAMS)[0]
    gap_h5, gap_split_h5 = write_scene(tmp_path / "gap", with_gt=True, tracks2d=True, no_train_frame_at=T_OBS + 1)
    gap_split = read_split(gap_split_h5)
    assert gap_split.frame_ids["train_future"].size == T - T_OBS - 1
    gap = tracking_section(model, fc, str(gap_h5), gap_split, EVAL_PARAMS)[0]
    assert full["aj"] < 1.0 and full["occlusion_accuracy"] < 1.0  # some points are predicted hidden
    assert gap == full and list(gap) == list(full)


def _scene_moved_at(folder: Path, inputs, steps) -> tuple[Path, Path, Path]:
    """scene.h5, split.h5 and priors.h5 of the inputs' scene with its cameras
    moved, its images changed and its ground truth shifted at time `steps`."""
    import dataclasses

    from mogaf.scene import load_scene, save_scene
    from mogaf.split import split_scene, write_split

    scene = load_scene(inputs["scene"], with_ground_truth=True)
    at = np.isin(scene.time_index, steps)
    w2c, images = scene.w2c.copy(), scene.images.copy()
    w2c[at, :3, 3] += [4.0, -3.0, 2.0]
    images[at] = 200
    gt = {"points3d": scene.ground_truth["points3d"].copy()}
    gt["points3d"][:, steps] += 1.0
    moved = dataclasses.replace(scene, w2c=w2c, images=images, ground_truth=gt)
    folder.mkdir()
    scene_h5 = save_scene(folder / "scene.h5", moved, config_digest="fc-test")
    split_h5 = write_split(folder / "split.h5", split_scene(scene_h5, RATIO))
    return scene_h5, split_h5, write_priors(folder / "priors.h5", scene_h5, split_h5)


def test_the_forecast_reads_nothing_of_the_future(inputs, tmp_path):
    """Cameras, images and ground truth changed at the forecast steps leave the
    structured MoGaF forecast (which reads the observed cameras) as it is;
    the same change at the observed steps moves it (so the check can fail)."""

    def forecast(name: str, scene_h5, split_h5, priors_h5) -> dict[str, np.ndarray]:
        out = run_forecast_group(
            str(inputs["model"]),
            str(inputs["groups"]),
            str(split_h5),
            str(tmp_path / f"{name}.h5"),
            MOGAF_FAST,
            method="mogaf",
            job="all",
            seed=0,
            scene_h5=str(scene_h5),
            priors_h5=str(priors_h5),
        )
        return _arrays(out)

    clean = forecast("clean", inputs["scene"], inputs["split"], inputs["priors"])
    future = forecast("future", *_scene_moved_at(tmp_path / "future", inputs, np.arange(T_OBS, T)))
    assert clean.keys() == future.keys()
    for k in clean:
        np.testing.assert_array_equal(clean[k], future[k], err_msg=k)
    observed = forecast("observed", *_scene_moved_at(tmp_path / "observed", inputs, np.arange(T_OBS)))
    assert not np.array_equal(clean["means"], observed["means"])


# ------------------------------------------------------------------ determinism
def test_same_inputs_same_seed_same_arrays(inputs, mogaf_parts, tmp_path):
    again = run_forecast_group(
        str(inputs["model"]),
        str(inputs["groups"]),
        str(inputs["split"]),
        str(tmp_path / "g.h5"),
        MOGAF_FAST,
        method="mogaf",
        job=Path(mogaf_parts[0]).stem.removeprefix("group"),
        seed=7,
        scene_h5=str(inputs["scene"]),
        priors_h5=str(inputs["priors"]),
    )
    a, b = _arrays(mogaf_parts[0]), _arrays(again)
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    m1 = _arrays(_merge(inputs, tmp_path / "m1.h5", mogaf_parts, "mogaf", MOGAF_FAST, seed=7))
    m2 = _arrays(_merge(inputs, tmp_path / "m2.h5", mogaf_parts, "mogaf", MOGAF_FAST, seed=7))
    for k in m1:
        np.testing.assert_array_equal(m1[k], m2[k], err_msg=k)
    c1 = _arrays(_merge(inputs, tmp_path / "c1.h5", [], "constant_velocity", seed=3))
    c2 = _arrays(_merge(inputs, tmp_path / "c2.h5", [], "constant_velocity", seed=3))
    for k in c1:
        np.testing.assert_array_equal(c1[k], c2[k], err_msg=k)
    # ... and the seed matters (so the comparison above can tell runs apart)
    other = run_forecast_group(
        str(inputs["model"]),
        str(inputs["groups"]),
        str(inputs["split"]),
        str(tmp_path / "o.h5"),
        MOGAF_FAST,
        method="mogaf",
        job=Path(mogaf_parts[0]).stem.removeprefix("group"),
        seed=8,
        scene_h5=str(inputs["scene"]),
        priors_h5=str(inputs["priors"]),
    )
    assert not np.array_equal(_arrays(other)["means"], a["means"])


def test_merges_and_untrained_forecasts_run_without_torch(inputs, mogaf_parts, tmp_path):
    """A merge job and the constant-velocity and frozen forecasts compute with
    NumPy alone: in a fresh process they never import torch (about 2.5 s per
    job, most of such a job's run time)."""
    import subprocess
    import sys

    code = f"""
import sys
from mogaf.forecast.stage import run_forecast_merge
args = ({str(inputs["model"])!r}, {str(inputs["groups"])!r}, {str(inputs["split"])!r})
run_forecast_merge(*args, {[str(p) for p in mogaf_parts]!r}, {str(tmp_path / "mogaf.h5")!r},
                   {{"groupwise": True, **{MOGAF_FAST!r}}}, method="mogaf", seed=7)
for method in ("constant_velocity", "frozen"):
    run_forecast_merge(*args, [], {str(tmp_path)!r} + f"/{{method}}.h5", {{}}, method=method, seed=0)
print("torch" in sys.modules)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
    assert {p.name for p in tmp_path.glob("*.h5")} == {"mogaf.h5", "constant_velocity.h5", "frozen.h5"}
