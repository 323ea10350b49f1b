"""`python -m mogaf.bench recon --score`: stored models of a results folder, scored without training."""

from __future__ import annotations

import shutil

import pytest

from mogaf.bench import recon as bench
from mogaf.split import read_split
from support.forecast_scene import write_model, write_scene


def test_score_results_folder(tmp_path, capsys):
    scene_h5, split_h5 = write_scene(tmp_path / "fc", with_gt=True)
    ratio_dir = tmp_path / "fc" / "ratio0.5"
    ratio_dir.mkdir()
    shutil.move(split_h5, ratio_dir / "split.h5")
    write_model(ratio_dir / "refined.h5", read_split(ratio_dir / "split.h5").observed_timesteps)
    assert bench.main(["--score", str(ratio_dir)]) == 0
    out = capsys.readouterr().out
    assert "fc/ratio0.5/refined.h5" in out and "recon.h5" not in out
    (row,) = bench.score_results(ratio_dir)
    # the GT points sit 0.01 from the rigid group's Gaussians and move with them
    assert row["traj_err"] == pytest.approx(0.01, abs=1e-6)
    assert row["ratio"] == 0.5 and row["wall_s"] is None and row["unseen_pct"] is None
    assert row["vel_err_mid"] == pytest.approx(0.0, abs=1e-6) and row["vel_err_last"] == pytest.approx(0.0, abs=1e-6)
    # an ablation variant's folder: split and scene are found above it
    variant = ratio_dir / "ablation" / "rt_fast"
    variant.mkdir(parents=True)
    shutil.copy(ratio_dir / "refined.h5", variant / "recon.h5")
    (row,) = bench.score_results(variant)
    assert row["scene"] == "fc/ratio0.5/ablation/rt_fast/recon.h5" and row["traj_err"] == pytest.approx(0.01, abs=1e-6)


def test_score_refuses_a_folder_that_is_not_a_results_folder(tmp_path, capsys):
    assert bench.main(["--score", str(tmp_path)]) == 1
    assert (
        "no split.h5 and scene.h5 above it (--score takes a results/<dataset>/<scene>/ratio<r> folder"
        in capsys.readouterr().err
    )


def test_velocity_error_sees_an_error_of_the_last_step_alone(tmp_path):
    """A model exact but for its last observed step, shifted by 0.02: the
    mid-window velocity error is nil, the last step's is the shift."""
    scene_h5, split_h5 = write_scene(tmp_path / "fc", with_gt=True)
    steps = read_split(split_h5).observed_timesteps
    model_h5 = write_model(tmp_path / "shifted.h5", steps, last_step_shift=0.02)
    matched = bench.matched_trajectories(scene_h5, split_h5, model_h5)
    mid, last = bench.velocity_error(*matched)
    assert mid == pytest.approx(0.0, abs=1e-6) and last == pytest.approx(0.02, abs=1e-6)
    # the mean position error sees it only as one step in many
    assert bench.trajectory_error(*matched)[0] < 0.01 + 0.02 / 4


@pytest.mark.parametrize(
    "argv, words",
    [
        (["--params", "notjson"], "--params is not JSON"),
        (["--mujoco-params", "[1]"], "--mujoco-params must be a JSON object"),
        (["--cases", " , "], "--cases ' , ': give synthetic[:PRESET] and/or mujoco/SCENE"),
        (["--cases", "synthetic,nope"], "--cases 'synthetic,nope'"),
    ],
)
def test_flags_are_checked_before_the_first_case_trains(tmp_path, capsys, argv, words):
    with pytest.raises(SystemExit) as exc:
        bench.main(["--workdir", str(tmp_path / "work"), *argv])
    assert exc.value.code == 2 and words in capsys.readouterr().err
    assert not (tmp_path / "work").exists()
