"""Fuzzing the dataset readers: whatever the JSON says, only MogafError escapes.

Malformed JSON, values of the wrong type or shape, negative focal lengths,
non-invertible or reflected poses and huge image sizes are written into tiny
fake datasets (a few 16x16 frames); each read must either succeed with a
valid scene or raise MogafError with one line naming a file.
"""

from __future__ import annotations

import json
import warnings
from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mogaf.datasets import read_scene
from mogaf.errors import MogafError
from support.fake_datasets import fake_dnerf, fake_iphone

FUZZ = settings(
    max_examples=60,
    deadline=timedelta(seconds=5),  # generous for loaded CI machines; a hang still fails
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)

numbers = st.one_of(
    st.integers(min_value=-(10**30), max_value=10**30),
    st.floats(allow_nan=False, allow_infinity=False),
    st.sampled_from([0, -1, 1e-300, 1e308, 10**9, 10**400, -0.0]),
)
json_values = st.recursive(
    st.one_of(st.none(), st.booleans(), numbers, st.text(max_size=8)),
    lambda inner: st.one_of(st.lists(inner, max_size=5), st.dictionaries(st.text(max_size=6), inner, max_size=4)),
    max_leaves=12,
)
matrices = st.one_of(
    st.lists(st.lists(numbers, min_size=4, max_size=4), min_size=4, max_size=4),  # mostly non-rigid
    st.lists(st.lists(numbers, min_size=0, max_size=5), min_size=0, max_size=5),  # ragged / wrong shapes
    st.builds(
        lambda s: (np.diag([s[0], s[1], s[2], 1.0])).tolist(), st.tuples(*[st.sampled_from([-1.0, 0.0, 1.0, 2.0])] * 3)
    ),
)
sizes = st.one_of(st.integers(min_value=-5, max_value=10**12), st.sampled_from([16, 12, 8, 10**9, 2**31, 2**64]))


def _check(layout: str, root: Path) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            scene = read_scene(layout, root, dataset="fuzz", scene="s", options={})
        except MogafError as exc:
            msg = str(exc)
            assert msg and "\n" not in msg
            return
    scene.validate(root)


@pytest.fixture(scope="module")
def dnerf_base(tmp_path_factory):
    return fake_dnerf(tmp_path_factory.mktemp("fuzz") / "dnerf", counts={"train": 2, "test": 1}, ply=None)


@pytest.fixture(scope="module")
def iphone_base(tmp_path_factory):
    return fake_iphone(tmp_path_factory.mktemp("fuzz") / "iphone", num_times=2, val_cameras=1, track_points=2)


class _Restore:
    """Rewrite one file for an example, restore it afterwards."""

    def __init__(self, path: Path):
        self.path = path
        self.original = path.read_bytes()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.path.write_bytes(self.original)


DNERF_KEYS = ["file_path", "time", "transform_matrix", "fl_x", "fl_y", "cx", "cy", "w", "h", "camera_angle_x"]


@FUZZ
@given(frame=st.integers(0, 1), key=st.sampled_from(DNERF_KEYS), value=json_values)
def test_fuzz_dnerf_frame_fields(dnerf_base, frame, key, value):
    path = dnerf_base / "transforms_train.json"
    with _Restore(path):
        data = json.loads(path.read_text())
        data["frames"][frame][key] = value
        path.write_text(json.dumps(data))
        _check("dnerf", dnerf_base)


@FUZZ
@given(
    matrix=matrices,
    focal=st.one_of(numbers, st.floats(max_value=0.0, allow_nan=False)),
    w=sizes,
    h=sizes,
    angle=numbers,
)
def test_fuzz_dnerf_poses_focals_sizes(dnerf_base, matrix, focal, w, h, angle):
    path = dnerf_base / "transforms_test.json"
    with _Restore(path):
        data = json.loads(path.read_text())
        data["camera_angle_x"] = angle
        data["frames"][0].update({"transform_matrix": matrix, "fl_x": focal, "w": w, "h": h})
        path.write_text(json.dumps(data))
        _check("dnerf", dnerf_base)


@FUZZ
@given(
    text=st.one_of(st.text(max_size=60), st.binary(max_size=60).map(lambda b: b.decode("latin-1"))),
    which=st.sampled_from(["transforms_train.json", "class_mapping.json"]),
)
def test_fuzz_dnerf_malformed_json_text(dnerf_base, text, which):
    path = dnerf_base / which
    with _Restore(path):
        path.write_bytes(text.encode("utf-8", errors="surrogatepass") if isinstance(text, str) else text)
        _check("dnerf", dnerf_base)


CAMERA_KEYS = [
    "orientation",
    "position",
    "focal_length",
    "principal_point",
    "pixel_aspect_ratio",
    "skew",
    "image_size",
    "radial_distortion",
    "tangential_distortion",
]


@FUZZ
@given(key=st.sampled_from(CAMERA_KEYS), value=json_values, name=st.sampled_from(["0_00000", "1_00000"]))
def test_fuzz_iphone_camera_fields(iphone_base, key, value, name):
    path = iphone_base / "camera" / f"{name}.json"
    with _Restore(path):
        cam = json.loads(path.read_text())
        cam[key] = value
        path.write_text(json.dumps(cam))
        _check("iphone", iphone_base)


@FUZZ
@given(
    orientation=st.one_of(matrices, st.lists(st.lists(numbers, min_size=3, max_size=3), min_size=3, max_size=3)),
    focal=numbers,
    size=st.lists(sizes, min_size=0, max_size=3),
    ratio=numbers,
)
def test_fuzz_iphone_poses_focals_sizes(iphone_base, orientation, focal, size, ratio):
    path = iphone_base / "camera" / "0_00001.json"
    with _Restore(path):
        cam = json.loads(path.read_text())
        cam.update({"orientation": orientation, "focal_length": focal, "image_size": size, "pixel_aspect_ratio": ratio})
        path.write_text(json.dumps(cam))
        _check("iphone", iphone_base)


@FUZZ
@given(
    which=st.sampled_from(
        ["splits/train.json", "splits/val.json", "metadata.json", "dataset.json", "scene.json", "extra.json"]
    ),
    key=st.sampled_from(
        ["frame_names", "camera_ids", "time_ids", "ids", "count", "0_00000", "center", "scale", "fps", "bbox"]
    ),
    value=json_values,
    whole=st.one_of(st.none(), st.text(max_size=40)),
)
def test_fuzz_iphone_metadata_files(iphone_base, which, key, value, whole):
    path = iphone_base / which
    with _Restore(path):
        if whole is not None:
            path.write_text(whole)
        else:
            data = json.loads(path.read_text())
            data[key] = value
            path.write_text(json.dumps(data))
        _check("iphone", iphone_base)
