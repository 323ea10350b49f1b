"""DyCheck iPhone reader: the real paper-windmill metadata (with tiny fake
images) and small fake scenes with Shape-of-Motion priors."""

from __future__ import annotations

import json
import os
import shutil
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from mogaf.camera import project, w2c_from_orientation_position
from mogaf.datasets import describe_missing, read_scene, scene_present
from mogaf.datasets.iphone import DistortionWarning, read_iphone_layout
from mogaf.errors import MogafError
from mogaf.scene import SPLIT_CODES, load_scene, save_scene
from support.fake_datasets import MARKER, fake_iphone, write_json
from support.paths import shared_path


def _windmill_farm(tmp_path: Path, scale: int) -> Path:
    """Symlinks to the real metadata plus black PNGs at rgb/<scale>x."""
    src = shared_path("dycheck-meta", "paper-windmill")
    root = tmp_path / "paper-windmill"
    root.mkdir()
    for entry in os.listdir(src):
        os.symlink(src / entry, root / entry)
    cam = json.loads((src / "camera" / "0_00000.json").read_text())
    W, H = cam["image_size"]
    assert W % scale == 0 and H % scale == 0
    ok, png = cv2.imencode(".png", np.zeros((H // scale, W // scale, 3), np.uint8))
    out = root / "rgb" / f"{scale}x"
    out.mkdir(parents=True)
    for name in os.listdir(src / "camera"):
        (out / name.replace(".json", ".png")).write_bytes(png.tobytes())
    return root


@pytest.mark.shared_data
def test_paper_windmill_metadata(tmp_path):
    # 720x960 divides by 16: 45x60 images keep the 696 fake PNGs tiny.
    root = _windmill_farm(tmp_path, 16)
    scene = read_scene("iphone", root, dataset="iphone", scene="paper-windmill", options={"scale": 16})
    assert scene.num_frames == 696 and scene.images.shape[1:] == (60, 45, 3)
    train = scene.source_split == SPLIT_CODES["train"]
    val = scene.source_split == SPLIT_CODES["val"]
    assert train.sum() == 277 and val.sum() == 419
    assert set(scene.camera_id[train]) == {0} and set(scene.camera_id[val]) == {1, 2}
    assert scene.num_timesteps == 277
    assert np.allclose(scene.time, scene.time_index / 276)
    splits = {s: json.loads((root / "splits" / f"{s}.json").read_text()) for s in ("train", "val")}
    assert scene.frame_names == splits["train"]["frame_names"] + splits["val"]["frame_names"]
    assert list(scene.time_index) == splits["train"]["time_ids"] + splits["val"]["time_ids"]
    # Cameras: K at 1/16 of the full-resolution json, w2c from orientation/position.
    for f in (0, 300, 695):
        cam = json.loads((root / "camera" / f"{scene.frame_names[f]}.json").read_text())
        fx = cam["focal_length"] / 16
        fy = fx * cam["pixel_aspect_ratio"]
        px, py = np.asarray(cam["principal_point"]) / 16
        assert np.allclose(scene.K[f], [[fx, cam["skew"] / 16, px], [0, fy, py], [0, 0, 1]])
        assert np.allclose(scene.w2c[f], w2c_from_orientation_position(cam["orientation"], cam["position"]))
    assert scene.meta["scene_scale"] == pytest.approx(0.2715916376300303) and scene.meta["fps"] == 30.0
    assert scene.meta["distortion"] == "none" and scene.alpha is None and scene.depth is None
    # The same metadata with images at 8x (90x120) is refused when asked for at 16x.
    shutil.rmtree(root / "rgb" / "16x")
    (root / "rgb" / "16x").mkdir()
    ok, png = cv2.imencode(".png", np.zeros((120, 90, 3), np.uint8))
    for name in scene.frame_names:
        (root / "rgb" / "16x" / f"{name}.png").write_bytes(png.tobytes())
    with pytest.raises(MogafError) as exc:
        read_scene("iphone", root, dataset="iphone", scene="paper-windmill", options={"scale": 16})
    assert "0_00000.png" in str(exc.value) and "90x120" in str(exc.value) and "45x60" in str(exc.value)


def test_fake_iphone_cameras_put_marker_on_its_pixel(fake_iphone_scene):
    root = fake_iphone_scene
    scene = read_iphone_layout(root, "fake", "s", {})
    markers = json.loads((root / "markers.json").read_text())
    for f, name in enumerate(scene.frame_names):
        uv, depth = project(MARKER[None], scene.K[f], scene.w2c[f])
        assert depth[0] > 0 and list(np.floor(uv[0]).astype(int)) == markers[name]
    assert len({tuple(v) for v in markers.values()}) > 3  # the marker moves across views


def test_colmap_aligned_disparity_needs_its_scale(tmp_path):
    root = fake_iphone(tmp_path / "s", num_times=3, val_cameras=0, colmap_scale=None)
    with pytest.raises(MogafError, match=r"aligned_depth_anything_colmap/2x.*COLMAP reconstruction.*colmap/scale\.npy"):
        read_scene("iphone", root, dataset="fake", scene="s", options={})
    (root / "flow3d_preprocessed" / "colmap").mkdir()
    for bad in (np.array([1.0, 2.0]), np.array(0.0), np.array(np.nan), np.array("2")):
        np.save(root / "flow3d_preprocessed" / "colmap" / "scale.npy", bad)
        with pytest.raises(MogafError, match=r"scale\.npy.*one finite positive number"):
            read_scene("iphone", root, dataset="fake", scene="s", options={})


def test_fake_iphone_layout_and_priors(tmp_path):
    root = fake_iphone(tmp_path / "s", num_times=5, val_cameras=2, track_points=3)
    scene = read_scene("iphone", root, dataset="fake", scene="s", options={})
    F = scene.num_frames
    assert F == 5 + 2 * 4 and scene.num_timesteps == 5
    train = np.flatnonzero(scene.source_split == SPLIT_CODES["train"])
    val = np.flatnonzero(scene.source_split == SPLIT_CODES["val"])
    assert list(train) == list(range(5)) and scene.images.shape[1:] == (12, 16, 3)
    assert scene.alpha is not None and np.all(scene.alpha == 255)
    # Depth on train frames only; covisible given on val frames, 1 on train.
    assert np.all(scene.depth[train] > 0) and np.all(scene.depth[val] == 0)
    assert np.all(scene.covisible[train] == 1) and set(np.unique(scene.covisible[val])) == {0, 1}
    # SoM foreground masks -> one instance.
    assert scene.instances.names == ["foreground"] and list(scene.instances.rigid) == [-1]
    assert set(np.unique(scene.instance_mask)) == {0, 1} and scene.instance_mask[0, 3:6, 4:8].all()
    # Disparity of the train frames.
    disp = scene.shipped["disparity"]
    assert list(disp["frame"]) == list(train) and disp["values"].shape == (5, 12, 16)
    # aligned to SoM's COLMAP reconstruction: divided by its scale.npy (2) to the camera jsons' units
    som_disp = root / "flow3d_preprocessed" / "aligned_depth_anything_colmap" / "2x"
    for row, f in enumerate(train):
        np.testing.assert_allclose(disp["values"][row], np.load(som_disp / f"{scene.frame_names[f]}.npy") / 2.0)
    assert list(disp["time_index"]) == list(scene.time_index[train])
    # Keypoints: pixel indices + 0.5; invisible ones are zero.
    kp = scene.shipped["keypoints"]
    assert kp["values"].shape == (5, 3, 3)
    assert np.allclose(kp["values"][0], [[1.5, 2.5, 1], [3.5, 1.5, 1], [0, 0, 0]])
    # Tracks: rows offsets[q]:offsets[q+1] hold query q's points over all targets.
    tr = scene.shipped["tracks_2d"]
    assert list(tr["offsets"]) == [0, 3, 6, 9, 12, 15] and tr["values"].shape == (15, 5, 4)
    assert list(tr["query_frame"]) == list(train) and list(tr["target_frame"]) == list(train)
    q = 2
    block = tr["values"][tr["offsets"][q] : tr["offsets"][q + 1]]
    assert np.allclose(block[:, :, 0], (np.arange(3) + q + 0.5)[:, None])  # x + 0.5 (pixel centres)
    assert np.allclose(block[:, :, 1], np.arange(5)[None, :] + 0.5)
    assert np.allclose(block[..., 2:], [-3.0, -2.0])
    # Metadata kept, world not rescaled.
    assert scene.meta["scene_scale"] == 0.5 and scene.meta["near"] == 0.1 and "not rescaled" in scene.meta["world"]


def test_fake_iphone_round_trip(tmp_path, fake_iphone_scene):
    root = fake_iphone_scene
    scene = read_scene("iphone", root, dataset="fake", scene="s", options={})
    save_scene(tmp_path / "scene.h5", scene, config_digest="t")
    back = load_scene(tmp_path / "scene.h5", with_shipped=True)
    assert np.array_equal(back.shipped["tracks_2d"]["values"], scene.shipped["tracks_2d"]["values"])
    assert np.array_equal(back.covisible, scene.covisible) and np.array_equal(back.depth, scene.depth)
    assert back.layout == "iphone" and back.meta["scale"] == 2


def test_tracks_options(tmp_path):
    root = fake_iphone(tmp_path / "s", num_times=6, track_points=10)
    scene = read_scene(
        "iphone", root, dataset="fake", scene="s", options={"tracks_query_stride": 2, "tracks_max_points": 4}
    )
    tr = scene.shipped["tracks_2d"]
    assert list(tr["query_frame"]) == [0, 2, 4] and list(tr["offsets"]) == [0, 4, 8, 12]
    assert np.allclose(tr["values"][:4, 0, 0], np.array([0, 3, 6, 9]) + 0.5)
    scene = read_scene(
        "iphone", root, dataset="fake", scene="s", options={"tracks": False, "priors": False, "depth": False}
    )
    # DyCheck's own keypoints stay; Shape-of-Motion priors and depth are skipped.
    assert set(scene.shipped) == {"keypoints"} and scene.instance_mask is None and scene.depth is None


def test_keypoints_at_2x_are_rescaled(tmp_path):
    root = fake_iphone(tmp_path / "s", scale=4, full_size=(32, 24))
    (root / "keypoint" / "4x").rename(root / "keypoint" / "2x")
    scene = read_scene("iphone", root, dataset="fake", scene="s", options={"scale": 4})
    # Stored as pixel indices at 2x: continuous (k + 0.5) * 2 / 4.
    assert np.allclose(scene.shipped["keypoints"]["values"][0, 0], [0.75, 1.25, 1])


def test_distortion_is_recorded_and_warned(fake_iphone_scene):
    root = fake_iphone_scene
    path = root / "camera" / "1_00002.json"
    cam = json.loads(path.read_text())
    cam["radial_distortion"] = [0.01, 0.0, 0.0]
    write_json(path, cam)
    with pytest.warns(DistortionWarning, match="1 of 13 cameras"):
        scene = read_scene("iphone", root, dataset="fake", scene="s", options={})
    row = scene.frame_names.index("1_00002")
    assert list(scene.shipped["distortion"]["frame"]) == [row]
    assert np.allclose(scene.shipped["distortion"]["radial"], [[0.01, 0, 0]])
    assert scene.meta["distortion"].startswith("ignored")


def test_rgb_without_alpha_and_no_val_split(tmp_path):
    root = fake_iphone(tmp_path / "s", rgba=False, val_cameras=0, covisible=False)
    os.remove(root / "splits" / "val.json")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = read_scene("iphone", root, dataset="fake", scene="s", options={})
    assert scene.alpha is None and set(scene.source_split) == {SPLIT_CODES["train"]} and scene.covisible is None


def test_iphone_missing_scene_message(tmp_path):
    missing = tmp_path / "apple"
    assert not scene_present("iphone", missing)
    msg = describe_missing("iphone", missing, "iphone", "apple")
    assert str(missing) in msg and "flow3d_preprocessed" in msg and "DyCheck" in msg and "\n" not in msg
    with pytest.raises(MogafError) as exc:
        read_scene("iphone", missing, dataset="iphone", scene="apple", options={})
    assert str(exc.value) == msg
