"""Every kind of bad dataset input gives one MogafError line naming the file."""

from __future__ import annotations

import json
import struct
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

from mogaf.datasets import read_scene
from mogaf.errors import MogafError
from support.fake_datasets import fake_dnerf, fake_iphone, write_json, write_png


def _fails(layout: str, root: Path, *fragments: str, options: dict | None = None) -> str:
    with pytest.raises(MogafError) as exc:
        read_scene(layout, root, dataset="fake", scene="s", options=options or {})
    assert type(exc.value) is MogafError
    msg = str(exc.value)
    assert "\n" not in msg and msg.strip() == msg
    for frag in fragments:
        assert frag in msg, f"{frag!r} not in {msg!r}"
    return msg


def _edit_json(path: Path, edit) -> None:
    data = json.loads(path.read_text())
    edit(data)
    write_json(path, data)


def _png_with_size(path: Path, width: int, height: int) -> None:
    """A PNG whose header announces width x height (no real pixel data)."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    chunk = b"IHDR" + ihdr
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + struct.pack(">I", len(ihdr)) + chunk + struct.pack(">I", zlib.crc32(chunk)))


# ---------------------------------------------------------------- D-NeRF
@pytest.fixture
def dnerf(tmp_path):
    return fake_dnerf(tmp_path / "s", counts={"train": 3, "test": 2})


def _frame(root: Path, split: str, i: int, edit) -> None:
    _edit_json(root / f"transforms_{split}.json", lambda d: edit(d["frames"][i]))


def test_dnerf_missing_folder(tmp_path):
    _fails("dnerf", tmp_path / "gone", str(tmp_path / "gone"), "transforms_train.json")


def test_dnerf_missing_train_json(dnerf):
    (dnerf / "transforms_train.json").unlink()
    _fails("dnerf", dnerf, "transforms_train.json", "missing")


def test_dnerf_image_named_in_json_but_absent(dnerf):
    (dnerf / "train" / "r_001.png").unlink()
    _fails("dnerf", dnerf, "r_001.png", "missing")


@pytest.mark.parametrize("content", [b"", b"not a png at all", b"\x89PNG\r\n\x1a\n\x00\x00", "truncated"])
def test_dnerf_corrupt_png(dnerf, content):
    path = dnerf / "test" / "r_001.png"
    if content == "truncated":
        content = path.read_bytes()[:-40]
    path.write_bytes(content)
    _fails("dnerf", dnerf, "r_001.png")


def test_dnerf_corrupt_png_data_crc(dnerf):
    path = dnerf / "train" / "r_002.png"
    raw = bytearray(path.read_bytes())
    i = raw.find(b"IDAT") + 10
    raw[i : i + 8] = b"\xff" * 8
    path.write_bytes(bytes(raw))
    _fails("dnerf", dnerf, "r_002.png")


def test_dnerf_malformed_json(dnerf):
    (dnerf / "transforms_test.json").write_text('{"camera_angle_x": 0.8, "frames": [')
    _fails("dnerf", dnerf, "transforms_test.json", "malformed JSON", "line 1")


def test_dnerf_nan_in_json(dnerf):
    text = (dnerf / "transforms_train.json").read_text().replace('"time": 0.0', '"time": NaN', 1)
    if "NaN" not in text:
        text = (dnerf / "transforms_train.json").read_text().replace('"camera_angle_x": 0.9', '"camera_angle_x": NaN')
    (dnerf / "transforms_train.json").write_text(text)
    _fails("dnerf", dnerf, "transforms_train.json")


def test_dnerf_infinite_time(dnerf):
    text = (dnerf / "transforms_test.json").read_text()
    data = json.loads(text)
    old = json.dumps(data["frames"][0]["time"])
    (dnerf / "transforms_test.json").write_text(text.replace(f'"time": {old}', '"time": 1e400', 1))
    _fails("dnerf", dnerf, "transforms_test.json", "time")


@pytest.mark.parametrize("key", ["fl_x", "camera_angle_x"])
def test_dnerf_negative_focal_length(dnerf, key):
    _frame(dnerf, "train", 1, lambda fr: fr.update({key: -300.0}))
    _fails("dnerf", dnerf, "transforms_train.json", key, "positive")


@pytest.mark.parametrize(
    "matrix, words",
    [
        ([[0, 0, 0, 1], [0, 0, 0, 2], [0, 0, 0, 3], [0, 0, 0, 1]], "not orthonormal"),
        ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, 4], [0, 0, 0, 1]], "reflection"),
        ([[2, 0, 0, 0], [0, 2, 0, 0], [0, 0, 2, 4], [0, 0, 0, 1]], "not orthonormal"),
        ([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 1, 1]], "bottom row"),
    ],
)
def test_dnerf_non_invertible_or_reflected_pose(dnerf, matrix, words):
    _frame(dnerf, "test", 0, lambda fr: fr.update({"transform_matrix": matrix}))
    _fails("dnerf", dnerf, "transforms_test.json", "frame 0", words)


@pytest.mark.parametrize(
    "matrix", [[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], [1, 2, 3], "eye", [[1, 0, 0, "a"]] * 4, None]
)
def test_dnerf_transform_matrix_wrong_shape(dnerf, matrix):
    _frame(dnerf, "train", 2, lambda fr: fr.update({"transform_matrix": matrix}))
    _fails("dnerf", dnerf, "transforms_train.json", "transform_matrix")


def test_dnerf_frames_not_a_list(dnerf):
    _edit_json(dnerf / "transforms_train.json", lambda d: d.update({"frames": {"a": 1}}))
    _fails("dnerf", dnerf, "transforms_train.json", "frames")


def test_dnerf_image_size_differs_from_json(dnerf):
    _frame(dnerf, "train", 0, lambda fr: fr.update({"w": 17, "h": 16}))
    _fails("dnerf", dnerf, "r_000.png", "transforms_train.json", "w=17")


def test_dnerf_image_size_differs_between_frames(dnerf):
    write_png(dnerf / "test" / "r_000.png", np.zeros((12, 16, 4), np.uint8))
    _fails("dnerf", dnerf, "r_000.png", "16x12", "expected 16x16")


@pytest.mark.parametrize("value", [10**9, 1e30, 10**400])
def test_dnerf_huge_size_in_json(dnerf, value):
    _frame(dnerf, "train", 0, lambda fr: fr.update({"w": value}))
    _fails("dnerf", dnerf, "transforms_train.json", "w ")


def test_dnerf_huge_size_in_png_header(dnerf):
    _png_with_size(dnerf / "train" / "r_000.png", 1_000_000_000, 1_000_000_000)
    _fails("dnerf", dnerf, "r_000.png", "implausible size")


def test_dnerf_mask_with_unlisted_id_and_missing_mask(dnerf):
    mask = np.zeros((16, 16), np.uint8)
    mask[3, 3] = 9
    write_png(dnerf / "train" / "masks" / "r_001.png", mask)
    _fails("dnerf", dnerf, "r_001.png", "id 9", "class_mapping.json")
    (dnerf / "train" / "masks" / "r_001.png").unlink()
    _fails("dnerf", dnerf, "r_001.png", "missing")


def test_dnerf_bad_class_mapping(dnerf):
    (dnerf / "class_mapping.json").write_text('{"zero": "background"}')
    _fails("dnerf", dnerf, "class_mapping.json", "'zero'")


def test_dnerf_bad_ply(dnerf):
    raw = (dnerf / "fused.ply").read_bytes()
    (dnerf / "fused.ply").write_bytes(raw.replace(b"element vertex 20", b"element vertex 2000000000"))
    _fails("dnerf", dnerf, "fused.ply", "vertices")
    (dnerf / "fused.ply").write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nend_header\n"
    )
    _fails("dnerf", dnerf, "fused.ply")
    (dnerf / "fused.ply").write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
        b"property float z\nproperty float x\nend_header\n" + bytes(16)
    )
    _fails("dnerf", dnerf, "fused.ply", "lists property 'x' twice")


def test_dnerf_bad_options(dnerf):
    _fails("dnerf", dnerf, "downscale", options={"downscale": 0})
    _fails("dnerf", dnerf, "background", options={"background": [1, 2]})
    _fails("dnerf", dnerf, "num_timesteps", options={"num_timesteps": "many"})


# ---------------------------------------------------------------- iPhone
@pytest.fixture
def iphone(tmp_path):
    return fake_iphone(tmp_path / "s", num_times=3, val_cameras=1)


def _camera(root: Path, name: str, edit) -> None:
    _edit_json(root / "camera" / f"{name}.json", edit)


def test_iphone_missing_folder(tmp_path):
    _fails("iphone", tmp_path / "apple", str(tmp_path / "apple"), "DyCheck", "flow3d_preprocessed")


def test_iphone_split_frame_without_camera(iphone):
    (iphone / "camera" / "0_00001.json").unlink()
    _fails("iphone", iphone, "0_00001.json", "missing camera", "splits/train.json")


def test_iphone_more_cameras_than_frames(iphone):
    write_json(iphone / "camera" / "3_00000.json", json.loads((iphone / "camera" / "0_00000.json").read_text()))
    _fails("iphone", iphone, "3_00000.json", "more cameras than frames")


def test_iphone_image_named_in_split_but_absent(iphone):
    (iphone / "rgb" / "2x" / "1_00001.png").unlink()
    _fails("iphone", iphone, "1_00001.png", "missing")


def test_iphone_corrupt_png(iphone):
    (iphone / "rgb" / "2x" / "0_00002.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 50)
    _fails("iphone", iphone, "0_00002.png")


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_iphone_non_finite_depth(iphone, bad):
    path = iphone / "depth" / "2x" / "0_00001.npy"
    d = np.load(path)
    d[2, 3] = bad
    np.save(path, d)
    _fails("iphone", iphone, "0_00001.npy", "NaN or infinite")


def test_iphone_corrupt_or_misshaped_npy(iphone):
    path = iphone / "depth" / "2x" / "0_00000.npy"
    np.save(path, np.ones((5, 5), np.float32))
    _fails("iphone", iphone, "0_00000.npy", "shape (5, 5)")
    path.write_bytes(b"\x93NUMPY garbage")
    _fails("iphone", iphone, "0_00000.npy", "corrupt")
    header = (
        b"\x93NUMPY\x01\x00"
        + struct.pack("<H", 118)
        + b"{'descr': '<f4', 'fortran_order': False, 'shape': (1000000, 1000000), }".ljust(117)
        + b"\n"
    )
    path.write_bytes(header)
    _fails("iphone", iphone, "0_00000.npy")


def test_iphone_non_finite_disparity(iphone):
    path = iphone / "flow3d_preprocessed" / "aligned_depth_anything_colmap" / "2x" / "0_00002.npy"
    d = np.load(path)
    d[0, 0] = np.nan
    np.save(path, d)
    _fails("iphone", iphone, "0_00002.npy", "NaN")


@pytest.mark.parametrize(
    "key, value, words",
    [
        ("focal_length", -500.0, "focal_length must be positive"),
        ("focal_length", "big", "focal_length must be a number"),
        ("pixel_aspect_ratio", 0.0, "pixel_aspect_ratio must be positive"),
        ("orientation", [[1, 0, 0], [0, 1, 0], [0, 0, 0]], "not orthonormal"),
        ("orientation", [[1, 0, 0], [0, 1, 0], [0, 0, -1]], "reflection"),
        ("orientation", [[1, 0, 0], [0, 1, 0]], "orientation"),
        ("position", [0, 0], "position"),
        ("principal_point", None, "principal_point"),
        ("image_size", [10**9, 10**9], "image_size width must be <="),
        ("image_size", [640], "image_size"),
        ("radial_distortion", [0.1, "x", 0], "radial_distortion"),
    ],
)
def test_iphone_bad_camera(iphone, key, value, words):
    _camera(iphone, "1_00000", lambda d: d.update({key: value}))
    _fails("iphone", iphone, "1_00000.json", words)


def test_iphone_malformed_json(iphone):
    (iphone / "camera" / "0_00000.json").write_text('{"focal_length": 10,,}')
    _fails("iphone", iphone, "0_00000.json", "malformed JSON")
    (iphone / "camera" / "0_00000.json").write_text("[1, 2]")
    _fails("iphone", iphone, "0_00000.json", "JSON object")
    (iphone / "splits" / "val.json").write_bytes(b"\xff\xfe\x00garbage")
    _fails("iphone", iphone, "val.json", "malformed JSON")


def test_iphone_split_lists_differ_in_length(iphone):
    _edit_json(iphone / "splits" / "train.json", lambda d: d["time_ids"].pop())
    _fails("iphone", iphone, "train.json", "differ in length")


def test_iphone_frame_in_two_splits(iphone):
    def dup(d):
        d["frame_names"].append("0_00000")
        d["camera_ids"].append(0)
        d["time_ids"].append(0)

    _edit_json(iphone / "splits" / "val.json", dup)
    _fails("iphone", iphone, "val.json", "listed twice")


def test_iphone_metadata_disagrees_with_split(iphone):
    _edit_json(iphone / "metadata.json", lambda d: d["1_00001"].update({"warp_id": 7}))
    _fails("iphone", iphone, "metadata.json", "1_00001", "warp_id")


def test_iphone_image_size_mismatch(iphone):
    write_png(iphone / "rgb" / "2x" / "1_00000.png", np.zeros((10, 16, 3), np.uint8))
    _fails("iphone", iphone, "1_00000.png", "16x10", "expected 16x12")


def test_iphone_huge_png_header(iphone):
    _png_with_size(iphone / "rgb" / "2x" / "0_00000.png", 80_000, 80_000)
    _fails("iphone", iphone, "0_00000.png", "implausible size")


def test_iphone_missing_scale_folder(iphone):
    _fails("iphone", iphone, "rgb/4x", "scale", options={"scale": 4})


def test_iphone_missing_track_file(iphone):
    (iphone / "flow3d_preprocessed" / "2d_tracks" / "2x" / "0_00001_0_00002.npy").unlink()
    _fails("iphone", iphone, "0_00001_0_00002.npy", "missing")


def test_synthetic_layout_without_its_module(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "mogaf.datasets.synthetic", None)
    _fails("synthetic", tmp_path, "mogaf.datasets.synthetic")


def test_overlong_names(dnerf, tmp_path):
    _frame(dnerf, "train", 0, lambda fr: fr.update({"file_path": "./" + "x" * 300 + "/r_000"}))
    _fails("dnerf", dnerf, "transforms_train.json", "too long")
    iphone = fake_iphone(tmp_path / "ip", num_times=2, val_cameras=1)
    _edit_json(iphone / "splits" / "val.json", lambda d: d["frame_names"].__setitem__(0, "n" * 300))
    _fails("iphone", iphone, "val.json", "plain file name")
