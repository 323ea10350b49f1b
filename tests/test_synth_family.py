"""The scene family (mogaf.synth.family) and the generator knobs it draws on:
motions that stop, and one to three held-out cameras."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import yaml

from mogaf.errors import MogafError
from mogaf.synth.family import CONTACT_KIND_NAMES, KIND_NAMES, family_scenes, family_yaml, main
from mogaf.synth.params import resolve_params
from mogaf.synth.world import build_world

ROOT = Path(__file__).resolve().parents[1]
FAMILY = ROOT / "config" / "family.yaml"


@pytest.fixture(scope="module")
def family() -> dict:
    return yaml.safe_load(FAMILY.read_text())


def test_the_committed_family_is_the_generators_output(capsys):
    # a hand edit of config/family.yaml, or a generator change, shows here
    assert main(["--count", "24", "--contact", "4", "--seed", "0", "--check", str(FAMILY)]) == 0
    assert FAMILY.read_text() == family_yaml(24, 0, 4)


def test_the_family_covers_every_kind_with_and_without_masks(family):
    scenes = family["synthetic"]
    assert len(scenes) >= 20
    kinds = Counter((name.split("_", 1)[1], params["ship_instance_masks"]) for name, params in scenes.items())
    assert {k for k, _ in kinds} == set(KIND_NAMES + CONTACT_KIND_NAMES)
    assert all(kinds[(k, True)] and kinds[(k, False)] for k in KIND_NAMES + CONTACT_KIND_NAMES)
    assert {len(p["test_camera_yaw_deg"]) for p in scenes.values()} == {1, 2, 3}
    assert len({p["num_frames"] for p in scenes.values()}) > 1
    assert len({p["seed"] for p in scenes.values()}) == len(scenes)
    # the family runs at both ratios, with the forecasts the acceptance compares, and keeps the demo scene
    assert family["grid"] == [{"dataset": "synthetic", "scenes": list(scenes), "ratios": [0.6, 0.8]}]
    assert family["forecast"]["methods"] == ["mogaf", "mogaf_paper", "constant_velocity", "frozen"]
    assert family["datasets"]["synthetic"]["scenes"] == ["default", *scenes]


def test_contact_scenes_come_after_the_first_ones_and_leave_them_as_drawn():
    first = family_scenes(3, 0)
    both = family_scenes(3, 0, contact=2)
    contact = ["f03_stick", "f04_stick", "f05_merge", "f06_merge"]  # each kind's scenes in turn
    assert list(both) == [*first, *contact]
    assert {name: both[name] for name in first} == first
    assert [both[n]["ship_instance_masks"] for n in contact] == [True, False, True, False]
    assert [both[n]["seed"] for n in contact] == [3, 4, 5, 6]
    assert all(0.6 < both[n]["stick_time"] < 0.8 for n in contact)  # between the two splits
    assert [both[n].get("stick_bodies", "spheres") for n in contact] == ["spheres", "spheres", "blobs", "blobs"]
    # more scenes per contact kind keep the first kind's (the later kinds' are numbered after them, drawn anew)
    more = family_scenes(3, 0, contact=3)
    assert {n: more[n] for n in ("f03_stick", "f04_stick")} == {n: both[n] for n in ("f03_stick", "f04_stick")}


def test_every_family_scene_builds(family):
    for name, params in family["synthetic"].items():
        world = build_world(resolve_params(params))
        assert world.num_cameras == 1 + len(params["test_camera_yaw_deg"]), name


def test_motion_stop_freezes_every_object_from_the_stop_on_and_changes_nothing_before():
    moving = build_world({"motion_stop": 1.0})
    stopped = build_world({"motion_stop": 0.7})
    default = build_world({})
    np.testing.assert_array_equal(moving.taus, default.taus)  # 1.0 is the generator as before
    stop = int(np.searchsorted(default.times, 0.7 * default.times[-1], side="right"))
    assert 0 < stop < len(default.times)
    np.testing.assert_array_equal(stopped.taus[:stop], default.taus[:stop])
    assert np.all(stopped.taus[stop:] == stopped.taus[stop]) and stopped.taus[stop] > stopped.taus[stop - 1]

    def centres(world, ti):
        return np.array([np.mean(p.extent_points(world.taus[ti]), axis=0) for p in world.objects])

    # objects keep their pose after the stop and follow the unstopped path before it
    last = len(stopped.taus) - 1
    np.testing.assert_allclose(centres(stopped, last), centres(stopped, stop), atol=1e-12)
    np.testing.assert_allclose(centres(stopped, stop - 1), centres(default, stop - 1), atol=1e-12)


def test_a_scene_with_bodies_that_meet_says_when_and_reads_back(tmp_path):
    from mogaf.datasets import read_scene
    from mogaf.synth.generate import generate_scene

    small = {"width": 48, "height": 36, "num_frames": 12, "num_track_points": 8, "supersample": 1}
    root = generate_scene(tmp_path / "merge", {**small, "stick_time": 0.7, "stick_bodies": "blobs"})
    scene = read_scene("synthetic", root, dataset="synthetic", scene="merge", options={"scale": 1})
    world = build_world(resolve_params({**small, "stick_time": 0.7, "stick_bodies": "blobs"}))
    assert (
        scene.meta["stick_time_s"] == pytest.approx(world.info["stick_time"])
        and scene.meta["sphere_bounce_times_s"] == []
    )
    assert list(scene.instances.names) == ["box", "blob", "blob_2", "cloth"]
    assert list(scene.instances.rigid) == [1, 0, 0, 0]  # the blobs are soft
    assert set(np.unique(scene.instance_mask)) >= {2, 4}  # both blobs are seen
    plain = generate_scene(tmp_path / "plain", small)
    assert (
        "stick_time_s"
        not in read_scene("synthetic", plain, dataset="synthetic", scene="plain", options={"scale": 1}).meta
    )


@pytest.mark.parametrize("yaws", [[20.0], [-24.0, 20.0, -6.0]])
def test_one_to_three_held_out_cameras_reach_the_scene_files(tmp_path, yaws):
    from mogaf.synth.generate import generate_scene

    root = generate_scene(
        tmp_path / "scene",
        {
            "width": 32,
            "height": 24,
            "num_frames": 6,
            "num_track_points": 8,
            "supersample": 1,
            "test_camera_yaw_deg": yaws,
        },
    )
    val = json.loads((Path(root) / "splits" / "val.json").read_text())
    assert sorted(set(val["camera_ids"])) == list(range(1, 1 + len(yaws)))
    assert len(val["frame_names"]) == 6 * len(yaws)
    assert np.load(Path(root) / "mogaf_gt" / "tracks2d_all.npy").shape[0] == 1 + len(yaws)


@pytest.mark.parametrize("yaws", [[], [1.0, 2.0, 3.0, 4.0], "20"])
def test_a_held_out_camera_list_of_the_wrong_length_is_one_clear_error(yaws):
    with pytest.raises(MogafError, match="'test_camera_yaw_deg' must be a list"):
        resolve_params({"test_camera_yaw_deg": yaws})


def test_the_family_command_says_bad_input_in_one_line_and_writes_nothing(tmp_path, capsys):
    assert main(["--count", "0"]) == 1
    assert capsys.readouterr().err.strip() == "mogaf.synth.family: error: scene family: count must be at least 1, got 0"
    target = tmp_path / "dir"
    target.mkdir()
    assert main(["--count", "1", "--contact", "0", "--write", str(target)]) == 1
    assert "is an existing directory" in capsys.readouterr().err and list(target.iterdir()) == []
    assert main(["--count", "1", "--contact", "0", "--check", str(tmp_path / "absent.yaml")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "absent.yaml: no such file" in err
    latin = tmp_path / "latin.yaml"
    latin.write_bytes(b"\xff")
    assert main(["--count", "1", "--contact", "0", "--check", str(latin)]) == 1
    assert f"{latin}: is not UTF-8 text (byte 0)" in capsys.readouterr().err
    assert main(["--count", "1", "--seed", "-1"]) == 1
    assert capsys.readouterr().err.strip() == "mogaf.synth.family: error: scene family: seed must be >= 0, got -1"
    assert main(["--count", "1", "--contact", "0", "--check", str(FAMILY)]) == 1  # one scene is not the committed 32
    assert "differs from the family drawn now" in capsys.readouterr().err
    assert main(["--count", "1", "--contact", "-1"]) == 1
    assert capsys.readouterr().err.strip() == "mogaf.synth.family: error: scene family: contact must be >= 0, got -1"
    assert main(["--count", "1", "--contact", "0", "--write", str(tmp_path / "f.yaml")]) == 0
    assert (tmp_path / "f.yaml").read_text() == family_yaml(1, 0) and sorted(p.name for p in tmp_path.iterdir()) == [
        "dir",
        "f.yaml",
        "latin.yaml",
    ]
