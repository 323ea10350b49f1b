"""D-NeRF reader: the five shared MuJoCo scenes, a projection check against
their object masks, and small fake scenes for the details."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from mogaf.camera import GL_TO_CV, camera_centers, project
from mogaf.datasets import describe_missing, read_scene, scene_present
from mogaf.datasets.common import time_grid
from mogaf.datasets.images import composite_downscale, downscale_labels
from mogaf.datasets.ply import read_ply_points
from mogaf.errors import MogafError
from mogaf.scene import SPLIT_CODES, load_scene, save_scene
from support.fake_datasets import MARKER, fake_dnerf, write_json, write_ply
from support.paths import shared_path

# about 20 s with two workers: collected early (tests/conftest.py)
pytestmark = pytest.mark.long(seconds=20)

MUJOCO = ("scene1_close_proximity", "scene3_collision", "scene4_occlusion", "scene5_rapid_motion", "scene7_deformation")


_READ: dict[str, object] = {}


def _mujoco(name: str):
    """A shared MuJoCo scene at downscale 4, read once per test session."""
    root = shared_path("mujoco", name)
    if name not in _READ:
        _READ[name] = read_scene("dnerf", root, dataset="mujoco", scene=name, options={"downscale": 4})
    return root, _READ[name]


@pytest.fixture(scope="module", params=MUJOCO)
def mujoco(request):
    return _mujoco(request.param)


# ---------------------------------------------------------------- MuJoCo
@pytest.mark.shared_data
def test_mujoco_scene_reads_and_matches_jsons(mujoco):
    root, scene = mujoco
    scene.validate(root)
    assert scene.images.shape[1:] == (200, 200, 3)
    all_times = []
    start = 0
    for split in ("train", "val", "test"):
        frames = json.loads((root / f"transforms_{split}.json").read_text())["frames"]
        rows = np.flatnonzero(scene.source_split == SPLIT_CODES[split])
        assert rows.size == len(frames)
        assert np.array_equal(rows, np.arange(start, start + len(frames)))
        start += len(frames)
        for row, fr in zip(rows, frames):
            assert scene.frame_names[row] == fr["file_path"][2:]
            assert scene.time[row] == fr["time"]
            # Intrinsics scaled exactly by 1/4, poses converted from OpenGL c2w.
            assert np.allclose(
                scene.K[row], [[fr["fl_x"] / 4, 0, fr["cx"] / 4], [0, fr["fl_y"] / 4, fr["cy"] / 4], [0, 0, 1]]
            )
            c2w_cv = np.asarray(fr["transform_matrix"]) @ GL_TO_CV
            assert np.allclose(scene.w2c[row] @ c2w_cv, np.eye(4), atol=1e-9)
        all_times += [fr["time"] for fr in frames]
    T = len(set(all_times))
    assert scene.num_timesteps == T
    assert np.array_equal(scene.time_index, np.rint(scene.time * (T - 1)).astype(int))
    assert np.array_equal(scene.camera_id, np.arange(scene.num_frames))
    mapping = json.loads((root / "class_mapping.json").read_text())
    assert scene.instances.names == [mapping[str(i)] for i in scene.instances.ids]
    assert 0 not in scene.instances.ids
    assert set(np.unique(scene.instance_mask)) <= {0, *scene.instances.ids.tolist()}
    assert scene.alpha is not None and scene.point_cloud.shape == (100000, 6)
    # Background is white where alpha is 0.
    bg = scene.alpha == 0
    assert bg.any() and np.all(scene.images[bg] == 255)


@pytest.mark.shared_data
def test_mujoco_scene_round_trips_through_scene_h5(tmp_path):
    root = shared_path("mujoco", "scene4_occlusion")
    scene = read_scene(
        "dnerf", root, dataset="mujoco", scene="scene4_occlusion", options={"downscale": 8, "frame_stride": 10}
    )
    assert scene.images.shape[1:3] == (100, 100)
    assert scene.num_timesteps == 120  # the grid uses every frame, not only those read
    save_scene(tmp_path / "scene.h5", scene, config_digest="test")
    back = load_scene(tmp_path / "scene.h5")
    assert np.array_equal(back.images, scene.images) and np.array_equal(back.instance_mask, scene.instance_mask)
    assert back.instances.names == scene.instances.names and back.meta["downscale"] == 8


def _sphere_axis(mask: np.ndarray, others: np.ndarray, K: np.ndarray, w2c: np.ndarray):
    """Silhouette cone of a sphere -> (camera centre, world ray to its centre, pixel of that ray).

    A sphere's silhouette rays all make the same angle with the ray through
    its centre, so that ray is the axis a with d_i . a = cos(alpha) for the
    unit rays d_i through the boundary pixels (linear least squares). This is
    exact for any sphere size and distance, unlike the mask centroid.
    Frames where the sphere touches another object or the border are skipped.
    """
    m = mask.astype(np.uint8)
    if m.sum() < 30 or m[0].any() or m[-1].any() or m[:, 0].any() or m[:, -1].any():
        return None
    if (cv2.dilate(m, np.ones((3, 3), np.uint8)).astype(bool) & others).any():
        return None
    contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if len(contours) != 1:
        return None
    pix = contours[0][:, 0, :].astype(np.float64) + 0.5
    d = np.c_[pix, np.ones(len(pix))] @ np.linalg.inv(K).T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    a = np.linalg.lstsq(d, np.ones(len(d)), rcond=None)[0]
    a /= np.linalg.norm(a)
    uv = (K @ a)[:2] / (K @ a)[2]
    return camera_centers(w2c), w2c[:3, :3].T @ a, uv


def _fit_trajectory(rays, ts):
    """Least-squares C(t) = c0 + c1 t + c2 t^2 meeting every ray (o, a)."""
    A, b = [], []
    for (o, a), t in zip(rays, ts):
        P = np.eye(3) - np.outer(a, a)
        A.append(np.kron(np.array([[1.0, t, t * t]]), P))
        b.append(P @ o)
    c = np.linalg.lstsq(np.vstack(A), np.concatenate(b), rcond=None)[0].reshape(3, 3)
    return lambda t: c[0] + c[1] * t + c[2] * t * t


def _sphere_reprojection_errors(scene, masks, K, w2c, window: int = 8) -> np.ndarray:
    """Triangulate each sphere over windows of consecutive time steps, reproject.

    Every D-NeRF frame has its own time, so a sphere is seen once per time
    step from a camera that moves from frame to frame. Over `window`
    consecutive steps its centre is fitted as a quadratic in time (ballistic
    motion is exactly quadratic) from the rays of all views; the fitted 3D
    point at each frame's time is projected with the frame's K and w2c and
    compared with the silhouette-cone centre found in that frame's mask.
    """
    errors = []
    order = np.argsort(scene.time_index, kind="stable")
    for iid, name in zip(scene.instances.ids, scene.instances.names):
        if not name.startswith("sphere"):
            continue
        obs = []
        for f in order:
            m = masks(f)
            r = _sphere_axis(m == iid, (m != iid) & (m != 0), K(f), w2c[f])
            obs.append(None if r is None else (f, *r))
        for i in range(0, len(obs) - window + 1, window):
            win = [o for o in obs[i : i + window] if o is not None]
            if len(win) < 6:
                continue
            ts = [scene.time[o[0]] - scene.time[win[0][0]] for o in win]
            C = _fit_trajectory([(o[1], o[2]) for o in win], ts)
            for o, t in zip(win, ts):
                uv, depth = project(C(t)[None], K(o[0]), w2c[o[0]])
                errors.append(np.linalg.norm(uv[0] - o[3]) if depth[0] > 0 else np.inf)
    return np.asarray(errors)


@pytest.mark.shared_data
def test_mujoco_spheres_reproject_onto_their_masks(mujoco):
    """Sphere centres triangulated from several views project within 1 px of
    where the (downscaled) object-id masks put them in each view."""
    _, scene = mujoco
    errors = _sphere_reprojection_errors(scene, lambda f: scene.instance_mask[f], lambda f: scene.K[f], scene.w2c)
    assert errors.size >= 12 and np.all(np.isfinite(errors))
    assert errors.max() < 1.0, f"max reprojection error {errors.max():.3f} px"
    assert np.median(errors) < 0.25


@pytest.mark.shared_data
def test_mujoco_projection_full_resolution_and_negative_control():
    """Same check at 800x800 on the original masks (K x 4 exactly); a camera
    left in OpenGL axes (no GL->CV flip) fails it by many pixels."""
    root, scene = _mujoco("scene1_close_proximity")

    def full_mask(f):
        split, stem = scene.frame_names[f].split("/")
        return cv2.imread(str(root / split / "masks" / f"{stem}.png"), cv2.IMREAD_UNCHANGED)

    def full_K(f):
        K = scene.K[f].copy()
        K[:2] *= 4
        return K

    errors = _sphere_reprojection_errors(scene, full_mask, full_K, scene.w2c)
    assert errors.size >= 30 and errors.max() < 1.0 and np.median(errors) < 0.1
    wrong = np.einsum("ij,fjk->fik", GL_TO_CV, scene.w2c)  # y and z axes not flipped
    bad = _sphere_reprojection_errors(scene, full_mask, full_K, wrong)
    assert bad.size == 0 or np.median(bad) > 5.0, f"negative control passed: median {np.median(bad):.3f} px"


# ---------------------------------------------------------------- fake scenes
def test_fake_scene_marker_lands_on_its_pixel(fake_dnerf_scene):
    root = fake_dnerf_scene
    scene = read_scene("dnerf", root, dataset="fake", scene="s", options={})
    jsons = {s: json.loads((root / f"transforms_{s}.json").read_text())["frames"] for s in ("train", "val", "test")}
    for f, name in enumerate(scene.frame_names):
        split, stem = name.split("/")
        fr = next(x for x in jsons[split] if x["file_path"] == f"./{split}/{stem}")
        uv, depth = project(MARKER[None], scene.K[f], scene.w2c[f])
        assert depth[0] > 0
        assert list(np.floor(uv[0]).astype(int)) == fr["marker_pixel"]
        col, row = fr["marker_pixel"]
        assert scene.instance_mask[f, row, col] == 2
    assert scene.num_timesteps == 8 and sorted(scene.time_index) == list(range(8))
    assert np.array_equal(np.bincount(scene.source_split), [4, 2, 2])


def test_fake_scene_background_alpha_and_downscale(tmp_path):
    root = fake_dnerf(tmp_path / "s", size=16)
    full = read_scene("dnerf", root, dataset="fake", scene="s", options={"background": [0, 0, 1]})
    half = read_scene("dnerf", root, dataset="fake", scene="s", options={"downscale": 2, "background": [0, 0, 1]})
    transparent = full.alpha == 0
    assert np.all(full.images[transparent] == [0, 0, 255])
    assert half.images.shape == (8, 8, 8, 3) and np.allclose(half.K[:, :2], full.K[:, :2] / 2)
    # Area rule: the half-size image is the block mean of the composited full image.
    blocks = full.images.astype(float).reshape(8, 8, 2, 8, 2, 3).mean(axis=(2, 4))
    assert np.abs(half.images - blocks).max() <= 1.0
    # Mask rule: every half-size id occurs in its 2x2 block.
    for f in range(8):
        for r in range(8):
            for c in range(8):
                assert half.instance_mask[f, r, c] in full.instance_mask[f, 2 * r : 2 * r + 2, 2 * c : 2 * c + 2]


def test_fake_scene_rgb_only_and_no_masks(tmp_path):
    root = fake_dnerf(tmp_path / "s", rgba=False, masks=False, ply=None)
    scene = read_scene("dnerf", root, dataset="fake", scene="s", options={})
    assert scene.alpha is None and scene.instance_mask is None and scene.instances is None and scene.point_cloud is None


def test_rigidity_patterns_first_match_wins(tmp_path):
    root = fake_dnerf(tmp_path / "s", class_names={0: "background", 1: "sphere_red", 2: "cloth"})
    opts = {"rigidity": {"sphere_*": "rigid", "*": "nonrigid"}}
    scene = read_scene("dnerf", root, dataset="fake", scene="s", options=opts)
    assert scene.instances.names == ["sphere_red", "cloth"] and list(scene.instances.rigid) == [1, 0]
    scene = read_scene("dnerf", root, dataset="fake", scene="s", options={"rigidity": {"cl*": "nonrigid"}})
    assert list(scene.instances.rigid) == [-1, 0]
    with pytest.raises(MogafError, match="rigidity"):
        read_scene("dnerf", root, dataset="fake", scene="s", options={"rigidity": {"*": "wobbly"}})


def test_per_frame_intrinsics_win_over_camera_angle(tmp_path):
    root = fake_dnerf(tmp_path / "s", counts={"train": 3})
    path = root / "transforms_train.json"
    data = json.loads(path.read_text())
    data["frames"][1].update({"fl_x": 20.0, "fl_y": 22.0, "cx": 7.5, "cy": 8.25, "w": 16, "h": 16})
    write_json(path, data)
    scene = read_scene("dnerf", root, dataset="fake", scene="s", options={"downscale": 2})
    assert np.allclose(scene.K[1], [[10.0, 0, 3.75], [0, 11.0, 4.125], [0, 0, 1]])
    assert np.isclose(scene.K[0, 0, 0], 0.5 * 16 / np.tan(0.45) / 2)


def test_time_grid_rules(tmp_path):
    src = tmp_path / "t.json"
    idx, T, err = time_grid(np.array([0.0, 0.5, 1.0, 0.25, 0.75]), src)
    assert T == 5 and list(idx) == [0, 2, 4, 1, 3] and err < 1e-9
    idx, T, _ = time_grid(np.array([0.0, 0.25, 1.0]), src)  # steps missing from the grid
    assert T == 5 and list(idx) == [0, 1, 4]
    with pytest.raises(MogafError, match="num_timesteps") as exc:
        time_grid(np.array([0.0, 0.3333, 0.71, 1.0]), src)
    assert "t.json" in str(exc.value)
    idx, T, err = time_grid(np.array([0.0, 0.3333, 0.71, 1.0]), src, num_timesteps=4)
    assert T == 4 and list(idx) == [0, 1, 2, 3] and 0.1 < err < 0.2
    assert time_grid(np.array([0.4, 0.4]), src)[1] == 1


def test_time_grid_option_snaps_dataset(tmp_path):
    root = fake_dnerf(tmp_path / "s", counts={"train": 3})
    path = root / "transforms_train.json"
    data = json.loads(path.read_text())
    for fr, t in zip(data["frames"], (0.0, 0.41, 1.0)):
        fr["time"] = t
    write_json(path, data)
    with pytest.raises(MogafError, match="uniform grid"):
        read_scene("dnerf", root, dataset="fake", scene="s", options={})
    scene = read_scene("dnerf", root, dataset="fake", scene="s", options={"num_timesteps": 3})
    assert list(scene.time_index) == [0, 1, 2] and scene.meta["time_snap_error"] > 0.1


@pytest.mark.parametrize("binary", [True, False])
def test_ply_binary_and_ascii(tmp_path, binary):
    xyz = np.array([[0.0, 1.0, 2.0], [-1.5, 2.5, 3.25]])
    write_ply(tmp_path / "p.ply", xyz, np.array([[255, 0, 51], [0, 255, 0]]), binary=binary)
    pts, colour = read_ply_points(tmp_path / "p.ply")
    assert colour and pts.shape == (2, 6) and np.allclose(pts[:, :3], xyz) and np.allclose(pts[0, 3:], [1, 0, 0.2])
    write_ply(tmp_path / "q.ply", xyz, None, binary=binary)
    pts, colour = read_ply_points(tmp_path / "q.ply")
    assert not colour and np.allclose(pts[:, 3:], 0.5)


def test_composite_and_label_downscale_helpers():
    rng = np.random.default_rng(0)
    rgba = rng.integers(0, 256, (8, 12, 4), dtype=np.uint8)
    bg = np.array([0.2, 0.4, 1.0])
    rgb, a = composite_downscale(rgba, bg, 4)
    al = rgba[..., 3:] / 255.0
    exact = (rgba[..., :3] * al + bg * 255 * (1 - al)).reshape(2, 4, 3, 4, 3).mean(axis=(1, 3))
    assert np.abs(rgb - exact).max() <= 0.51 and rgb.shape == (2, 3, 3) and a.shape == (2, 3)
    labels = np.array([[0, 0, 3, 3], [0, 5, 3, 5]], dtype=np.int32)
    assert downscale_labels(labels, 2).tolist() == [[0, 3]]
    tie = np.array([[7, 2], [2, 7]], dtype=np.int32)
    assert downscale_labels(tie, 2).tolist() == [[2]]  # ties go to the smallest id


def test_registry_missing_scene_and_unknown_layout(tmp_path):
    missing = tmp_path / "nowhere"
    assert not scene_present("dnerf", missing)
    msg = describe_missing("dnerf", missing, "mujoco", "scene1")
    assert str(missing) in msg and "transforms_train.json" in msg and "\n" not in msg
    with pytest.raises(MogafError) as exc:
        read_scene("dnerf", missing, dataset="mujoco", scene="scene1", options={})
    assert str(exc.value) == msg
    with pytest.raises(MogafError, match="unknown dataset layout"):
        read_scene("colmap", tmp_path, dataset="x", scene="y", options={})
