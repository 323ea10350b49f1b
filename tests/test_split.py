"""The forecast split: protocols, roles, and that later stages read only their rows."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from mogaf.artefact import read_dataset, time_steps_index
from mogaf.errors import MogafError
from mogaf.scene import SPLIT_CODES, Scene, save_scene
from mogaf.split import (
    load_evenly_spaced_frames,
    load_frames,
    load_ground_truth,
    make_split,
    read_split,
    split_scene,
    write_split,
)


def iphone_meta(T=60):
    ti = np.tile(np.arange(T), 3)
    cam = np.repeat([0, 1, 2], T)
    ss = np.where(cam == 0, SPLIT_CODES["train"], SPLIT_CODES["val"])
    return ti / (T - 1), ti, T, ss, cam


def test_iphone_protocol_counts():
    sp = make_split(*iphone_meta(60), layout="iphone", ratio=0.6)
    assert sp.observed_timesteps.tolist() == list(range(36))
    assert sp.forecast_timesteps.tolist() == list(range(36, 60))
    assert sp.frame_ids["observed"].tolist() == list(range(36))  # camera 0, t < 36
    ev = sp.frame_ids["evaluation"]
    assert len(ev) == 2 * 24 and all(i >= 60 for i in ev)  # held-out cameras only, t >= 36
    assert len(sp.frame_ids["evaluation_observed"]) == 2 * 36
    assert sp.frame_ids["train_future"].tolist() == list(range(36, 60))


def test_dnerf_protocol_uses_train_and_test_after_the_cut():
    T = 10
    ti = np.arange(T)
    # train frames at even steps, test at odd steps, one val frame at step 9
    ss = np.where(ti % 2 == 0, SPLIT_CODES["train"], SPLIT_CODES["test"])
    ss[9] = SPLIT_CODES["val"]
    sp = make_split(ti / (T - 1), ti, T, ss, ti, layout="dnerf", ratio=0.5)
    # time < 0.5 -> steps 0..4 (4/9 < 0.5 <= 5/9)
    assert sp.observed_timesteps.tolist() == [0, 1, 2, 3, 4]
    assert sp.frame_ids["observed"].tolist() == [0, 2, 4]
    assert sp.frame_ids["evaluation"].tolist() == [5, 6, 7, 8]  # val frame 9 is not used
    assert sp.frame_ids["evaluation_observed"].tolist() == [1, 3]


@pytest.mark.parametrize("ratio", [0.0, 1.0, 1.5, -0.2, float("nan")])
def test_ratio_outside_unit_interval(ratio):
    with pytest.raises(MogafError, match="outside"):
        make_split(*iphone_meta(), layout="iphone", ratio=ratio)


def test_too_few_observed_steps():
    with pytest.raises(MogafError, match="at least 3"):
        make_split(*iphone_meta(10), layout="iphone", ratio=0.15)


def _tiny_scene(T=8, H=6, W=5):
    F = 2 * T
    ti = np.tile(np.arange(T), 2)
    w2c = np.repeat(np.eye(4)[None], F, axis=0)
    w2c[:, 2, 3] = 3.0
    K = np.repeat(np.array([[10.0, 0, 2.5], [0, 10.0, 3.0], [0, 0, 1]])[None], F, axis=0)
    rng = np.random.default_rng(0)
    return Scene(
        dataset="toy",
        name="s",
        layout="iphone",
        frame_names=[f"{c}_{t:05d}" for c in (0, 1) for t in range(T)],
        images=rng.integers(0, 255, (F, H, W, 3), dtype=np.uint8),
        K=K,
        w2c=w2c,
        time=ti / (T - 1),
        time_index=ti,
        num_timesteps=T,
        camera_id=np.repeat([0, 1], T),
        source_split=np.repeat([0, 1], T).astype(np.int8),
        depth=np.ones((F, H, W), np.float32),
        ground_truth={"points3d": rng.normal(size=(4, T, 3)), "visible": np.ones((4, T), bool)},
    )


def test_later_stages_read_only_their_rows(tmp_path):
    scene_h5 = save_scene(tmp_path / "scene.h5", _tiny_scene(), config_digest="d")
    sp = split_scene(scene_h5, 0.5)
    write_split(tmp_path / "split.h5", sp)
    sp = read_split(tmp_path / "split.h5")
    future = np.setdiff1d(np.arange(16), sp.frame_ids["observed"])
    with h5py.File(scene_h5, "r+") as fh:  # poison every frame a training stage must not see
        for key in ("K", "w2c", "time"):
            ds = fh[f"frames/{key}"]
            for row in future:
                ds[row] = np.nan
    obs = load_frames(scene_h5, sp, "observed")
    assert obs.num_frames == 4 and np.all(np.isfinite(obs.K))
    with pytest.raises(MogafError, match="non-finite values in the requested rows"):
        load_frames(scene_h5, sp, "evaluation")


def test_ground_truth_cut_to_its_part(tmp_path):
    scene = _tiny_scene()
    scene_h5 = save_scene(tmp_path / "scene.h5", scene, config_digest="d")
    sp = split_scene(scene_h5, 0.5)
    obs = load_ground_truth(scene_h5, sp, "observed")
    fut = load_ground_truth(scene_h5, sp, "forecast")
    np.testing.assert_allclose(obs["points3d"], scene.ground_truth["points3d"][:, :4])
    np.testing.assert_allclose(fut["points3d"], scene.ground_truth["points3d"][:, 4:])


def test_ground_truth_reads_only_its_part_from_disk(tmp_path):
    scene_h5 = save_scene(tmp_path / "scene.h5", _tiny_scene(), config_digest="d")
    sp = split_scene(scene_h5, 0.5)
    with h5py.File(scene_h5, "r+") as fh:  # poison the future steps: reading them would fail the finite check
        fh["ground_truth/points3d"][:, 4:] = np.nan
    obs = load_ground_truth(scene_h5, sp, "observed")
    assert obs["points3d"].shape == (4, 4, 3) and np.all(np.isfinite(obs["points3d"]))
    with pytest.raises(MogafError, match="points3d' contains non-finite values"):
        load_ground_truth(scene_h5, sp, "forecast")


def test_ground_truth_entries_are_read_alone(tmp_path):
    scene_h5 = save_scene(tmp_path / "scene.h5", _tiny_scene(), config_digest="d")
    sp = split_scene(scene_h5, 0.5)
    with h5py.File(scene_h5, "r+") as fh:  # an entry not asked for is never read
        fh["ground_truth/points3d"][...] = np.nan
    assert load_ground_truth(scene_h5, sp, "observed", entries=("visible", "nope")).keys() == {"visible"}
    with pytest.raises(MogafError, match="points3d' contains non-finite values"):
        load_ground_truth(scene_h5, sp, "observed", entries=("points3d",))


def test_time_steps_index_reads_a_range_as_one_slice():
    assert time_steps_index(np.arange(3, 7)) == slice(3, 7)
    assert time_steps_index(np.zeros(0, np.int64)) == slice(0, 0)
    np.testing.assert_array_equal(time_steps_index(np.array([1, 4, 5])), [1, 4, 5])
    with pytest.raises(MogafError, match="not increasing"):
        time_steps_index(np.array([4, 1]))
    with pytest.raises(MogafError, match="outside the time axis of 6"):
        time_steps_index(np.arange(4, 7), 6)  # a slice past the end would silently read fewer steps


def test_read_dataset_reads_only_the_selected_strings(tmp_path):
    with h5py.File(tmp_path / "s.h5", "w") as fh:
        fh["names"] = np.array(["a", "b", "c"], dtype=h5py.string_dtype())
    with h5py.File(tmp_path / "s.h5", "r") as fh:
        assert read_dataset(fh["names"], tmp_path / "s.h5", sel=slice(0, 2)) == ["a", "b"]
        assert read_dataset(fh["names"], tmp_path / "s.h5") == ["a", "b", "c"]


@pytest.mark.parametrize("limit, expect", [(0, 4), (2, 2), (3, 3), (4, 4), (20, 4)])
def test_evenly_spaced_frames_span_the_role(tmp_path, limit, expect):
    scene_h5 = save_scene(tmp_path / "scene.h5", _tiny_scene(), config_digest="d")
    sp = split_scene(scene_h5, 0.5)
    frames = load_evenly_spaced_frames(scene_h5, sp, "evaluation", limit)
    assert frames.num_frames == expect
    rows = sp.frame_ids["evaluation"]
    assert (
        frames.frame_names[0] == f"1_{int(rows[0]) - 8:05d}" and frames.frame_names[-1] == f"1_{int(rows[-1]) - 8:05d}"
    )


def test_a_split_of_another_scene_is_refused(tmp_path):
    scene_h5 = save_scene(tmp_path / "a.h5", _tiny_scene(), config_digest="d")
    sp = split_scene(scene_h5, 0.5)
    reversed_scene = _tiny_scene()
    reversed_scene.time_index = reversed_scene.time_index[::-1].copy()  # same rows, other time steps
    reversed_scene.time = reversed_scene.time[::-1].copy()
    other = save_scene(tmp_path / "b.h5", reversed_scene, config_digest="d")
    with pytest.raises(
        MogafError, match=r"b\.h5: frame 0 of split role 'observed' is at time step 7, outside .*another scene"
    ):
        load_frames(other, sp, "observed")
    longer = save_scene(tmp_path / "c.h5", _tiny_scene(T=10), config_digest="d")
    for call in (lambda: load_frames(longer, sp, "observed"), lambda: load_ground_truth(longer, sp, "observed")):
        with pytest.raises(MogafError, match=r"c\.h5: has 10 time steps, the split has 8"):
            call()
