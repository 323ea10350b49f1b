"""mogaf.synth: the embedded synthetic generator and its reader (mogaf.datasets.synthetic)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from mogaf.camera import project
from mogaf.errors import MogafError
from mogaf.synth import DEFAULT_PARAMS, PRESETS, resolve_params
from mogaf.synth.generate import generate_scene
from mogaf.synth.world import build_world, check_world

SMALL = {"width": 64, "height": 48, "num_frames": 6, "supersample": 1, "num_track_points": 16}


def _tree_digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def default_dir(tmp_path_factory) -> Path:
    return generate_scene(tmp_path_factory.mktemp("synth") / "default", {"preset": "default"})


@pytest.fixture(scope="module")
def scene(default_dir):
    from mogaf.datasets import read_scene

    return read_scene("synthetic", default_dir, dataset="synthetic", scene="default", options={"scale": 1})


def _kabsch_residual(a: np.ndarray, b: np.ndarray) -> float:
    """Max distance after the best rigid alignment of a onto b (both (N, 3))."""
    ca, cb = a.mean(0), b.mean(0)
    U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return float(np.abs((a - ca) @ R.T + cb - b).max())


# ---------------------------------------------------------------- params
def test_params_defaults_presets_and_errors():
    p = resolve_params({})
    assert (p["width"], p["height"], p["num_frames"], p["nonrigid"]) == (160, 120, 60, "cloth")
    hard = resolve_params({"preset": "hard"})
    assert hard["num_frames"] > p["num_frames"] and hard["speed"] > p["speed"] and hard["num_extra_objects"] > 0
    assert set(PRESETS) >= {"default", "hard"} and set(DEFAULT_PARAMS) == set(p)
    assert resolve_params({"preset": "hard", "num_frames": 30})["num_frames"] == 30
    for bad in (
        {"bogus": 1},
        {"preset": "nope"},
        {"nonrigid": "jelly"},
        {"num_frames": 1},
        {"width": 10.5},
        {"box_velocity": [1, 2]},
    ):
        with pytest.raises(MogafError):
            resolve_params(bad)


def test_worlds_keep_objects_in_view_and_apart():
    """build_world refuses worlds where an object leaves a view; presets and variants pass."""
    for params in (
        {},
        {"preset": "hard"},
        {"nonrigid": "arm"},
        {"preset": "hard", "seed": 3, "num_extra_objects": 6},
        {"num_frames": 200},
    ):
        world = build_world(resolve_params(params))
        assert check_world(world) is None
    hard = build_world(resolve_params({"preset": "hard"}))
    duration = (hard.params.num_frames - 1) / hard.params.fps
    bounces = hard.info["sphere_bounce_times"]
    assert any(b > 0.6 * duration for b in bounces), "hard preset: a bounce falls in the forecast part"
    assert len(hard.objects) == 3 + hard.params.num_extra_objects
    assert build_world(resolve_params({})).info["sphere_bounce_times"] == []


# ---------------------------------------------------------------- layout + reader
def test_layout_files(default_dir):
    T = DEFAULT_PARAMS["num_frames"]
    for rel in (
        "dataset.json",
        "metadata.json",
        "scene.json",
        "extra.json",
        "splits/train.json",
        "splits/val.json",
        "points.npy",
        "mogaf_gt/instances.json",
    ):
        assert (default_dir / rel).is_file(), rel
    assert len(list((default_dir / "camera").glob("*.json"))) == 3 * T
    assert len(list((default_dir / "rgb/1x").glob("*.png"))) == 3 * T
    assert len(list((default_dir / "covisible/1x/val").glob("*.png"))) == 2 * T
    assert len(list((default_dir / "flow3d_preprocessed/track_anything/1x").glob("*.png"))) == 3 * T
    cam = json.loads((default_dir / "camera/0_00000.json").read_text())
    assert cam["image_size"] == [160, 120] and cam["principal_point"] == [80.0, 60.0]
    depth = np.load(default_dir / "depth/1x/1_00007.npy")
    assert depth.shape == (120, 160, 1) and depth.dtype == np.float32
    inst = cv2.imread(str(default_dir / "mogaf_gt/instance/1x/2_00010.png"), cv2.IMREAD_UNCHANGED)
    assert inst.dtype == np.uint16 and inst.shape == (120, 160)
    part = cv2.imread(str(default_dir / "mogaf_gt/part/1x/2_00010.png"), cv2.IMREAD_UNCHANGED)
    assert part.dtype == np.uint8 and part.shape == (120, 160) and not part.any(), "every object is one piece"
    val = json.loads((default_dir / "splits/val.json").read_text())
    assert set(val["camera_ids"]) == {1, 2} and len(val["frame_names"]) == 2 * T
    assert not list(default_dir.parent.glob(".default.tmp-*")), "no temporary folder is left behind"


def test_reads_back_through_the_registry(scene):
    T = DEFAULT_PARAMS["num_frames"]
    assert scene.layout == "iphone" and scene.num_frames == 3 * T and scene.num_timesteps == T
    assert (scene.height, scene.width) == (120, 160)
    assert list(scene.instances.names) == ["box", "sphere", "cloth"]
    assert scene.instances.rigid.tolist() == [1, 1, 0]
    assert scene.instance_mask.shape == (3 * T, 120, 160)
    assert set(np.unique(scene.instance_mask).tolist()) == {0, 1, 2, 3}
    assert np.all(np.isfinite(scene.depth)) and scene.depth.min() > 0.5 and scene.depth.max() < 20
    assert scene.covisible is not None
    val = scene.source_split == 1
    assert val.sum() == 2 * T and np.all(scene.covisible[~val] == 1)
    frac = scene.covisible[val].mean()
    assert 0.3 < frac < 0.98, frac
    gt = scene.ground_truth
    P = gt["points3d"].shape[0]
    assert gt["points3d"].shape == (P, T, 3) and gt["tracks2d"].shape == (P, T, 2) and gt["visible"].shape == (P, T)
    assert gt["object_poses"].shape == (2, T, 4, 4) and gt["object_pose_ids"].tolist() == [1, 2]
    assert gt["camera1"]["tracks2d"].shape == (P, T, 2)
    assert 0.3 < gt["visible"].mean() < 0.95
    # every dynamic object is seen (not clipped by the border) in every frame of every camera
    for f in range(scene.num_frames):
        m = scene.instance_mask[f]
        border = np.concatenate([m[0], m[-1], m[:, 0], m[:, -1]])
        assert not border.any(), f"frame {scene.frame_names[f]}: an object touches the border"
        counts = np.bincount(m.ravel(), minlength=4)
        assert np.all(counts[1:] >= 15), (scene.frame_names[f], counts)


def _box_face(world_pts: np.ndarray, pose: np.ndarray, half: np.ndarray) -> np.ndarray:
    q = ((world_pts - pose[:3, 3]) @ pose[:3, :3]) / half
    axis = np.argmax(np.abs(q), axis=1)
    return 2 * axis + (q[np.arange(len(q)), axis] > 0)


def _unproject(K, w2c, col, row, depth):
    cam = np.stack([(col + 0.5 - K[0, 2]) / K[0, 0] * depth, (row + 0.5 - K[1, 2]) / K[1, 1] * depth, depth], axis=1)
    return (cam - w2c[:3, 3]) @ w2c[:3, :3]


def test_known_points_project_where_the_renderer_put_them(scene, default_dir):
    """Acceptance: GT surface points, projected through the cameras the reader
    returns, land (within 1 px) on pixels the renderer gave their instance id,
    at the depth of the point; the 2D tracks are those projections."""
    gt = scene.ground_truth
    pts, inst = gt["points3d"].astype(np.float64), gt["points_instance"]
    H, W = scene.height, scene.width
    half = np.array(
        json.loads((default_dir / "mogaf_gt/instances.json").read_text())["instances"][0]["shape"]["half_extents"]
    )
    box_pose = gt["object_poses"][list(gt["object_pose_ids"]).index(1)]
    checked = 0
    for cam, vis_all in ((0, gt["visible"]), (1, gt["camera1"]["visible"]), (2, gt["camera2"]["visible"])):
        frames = {int(t): f for f in np.flatnonzero(scene.camera_id == cam) for t in [scene.time_index[f]]}
        for t in range(0, scene.num_timesteps, 7):
            f = frames[t]
            uv, z = project(pts[:, t], scene.K[f], scene.w2c[f])
            if cam == 0:
                np.testing.assert_allclose(gt["tracks2d"][:, t], uv, atol=2e-3)
            vis = vis_all[:, t]
            assert vis.sum() > 50
            col, row = np.floor(uv[vis]).astype(int).T
            ids = inst[vis]
            same_centre = scene.instance_mask[f, row, col] == ids
            # the pixel containing the projection carries the point's id, except on silhouettes
            assert same_centre.mean() > 0.9, (cam, t, same_centre.mean())
            for k in range(int(vis.sum())):
                r0, r1, c0, c1 = max(row[k] - 1, 0), min(row[k] + 2, H), max(col[k] - 1, 0), min(col[k] + 2, W)
                assert (scene.instance_mask[f, r0:r1, c0:c1] == ids[k]).any()
            # inverse depth, bilinear between the 4 pixel centres around the projection (exact on
            # planes, where 1/z is affine in the image), is the point's inverse depth
            q = uv[vis] - 0.5
            c0, r0 = np.floor(q).astype(int).T
            a, b = (q - np.floor(q)).T
            inside = (c0 >= 0) & (r0 >= 0) & (c0 + 1 < W) & (r0 + 1 < H)
            c0, r0, a, b, ids_in, z_in = c0[inside], r0[inside], a[inside], b[inside], ids[inside], z[vis][inside]
            quad = [
                (r0, c0, (1 - a) * (1 - b)),
                (r0, c0 + 1, a * (1 - b)),
                (r0 + 1, c0, (1 - a) * b),
                (r0 + 1, c0 + 1, a * b),
            ]
            same = np.all([scene.instance_mask[f, r, c] == ids_in for r, c, _ in quad], axis=0)
            inv = sum(w / scene.depth[f, r, c].astype(np.float64) for r, c, w in quad)
            rel = np.abs(1.0 / inv - z_in) / z_in
            # box: where the 4 pixel centres lie on the point's face (a plane), exact
            box = same & (ids_in == 1)
            face = _box_face(pts[vis][inside][box, t], box_pose[t], half)
            on_face = [
                _box_face(
                    _unproject(
                        scene.K[f], scene.w2c[f], c[box], r[box], scene.depth[f, r[box], c[box]].astype(np.float64)
                    ),
                    box_pose[t],
                    half,
                )
                == face
                for r, c, _ in quad
            ]
            one_face = np.all(on_face, axis=0)
            assert one_face.sum() > 10
            assert rel[box][one_face].max() < 1e-5, (cam, t, rel[box][one_face].max())
            # curved sphere / cloth: second-order error only
            for k in (2, 3):
                sel = same & (ids_in == k)
                if sel.sum() > 10:
                    assert np.median(rel[sel]) < 1e-3, (cam, t, k)
            checked += int(same.sum())
    assert checked > 1000


def test_depth_maps_lie_on_the_rigid_surfaces(scene, default_dir):
    """Back-projecting pixel centres with the reader's K, w2c and the depth maps
    puts them exactly on the sphere / box surfaces at their GT poses (this pins
    the +0.5 pixel-centre convention and the pose ground truth)."""
    info = json.loads((default_dir / "mogaf_gt/instances.json").read_text())["instances"]
    shapes = {d["id"]: d["shape"] for d in info}
    poses = dict(zip(scene.ground_truth["object_pose_ids"].tolist(), scene.ground_truth["object_poses"]))
    H, W = scene.height, scene.width
    jj, ii = np.mgrid[0:H, 0:W]
    for f in range(0, scene.num_frames, 11):
        t = int(scene.time_index[f])
        K, w2c, depth = scene.K[f], scene.w2c[f], scene.depth[f].astype(np.float64)
        for inst_id in (1, 2):
            m = scene.instance_mask[f] == inst_id
            z = depth[m]
            cam = np.stack([(ii[m] + 0.5 - K[0, 2]) / K[0, 0] * z, (jj[m] + 0.5 - K[1, 2]) / K[1, 1] * z, z], axis=1)
            world = (cam - w2c[:3, 3]) @ w2c[:3, :3]
            pose = poses[inst_id][t]
            local = (world - pose[:3, 3]) @ pose[:3, :3]
            tol = 2e-6 * z.max() + 1e-6
            if inst_id == 2:
                err = np.abs(np.linalg.norm(local, axis=1) - shapes[inst_id]["radius"])
            else:
                err = np.abs(np.abs(local / np.array(shapes[inst_id]["half_extents"])).max(axis=1) - 1.0) * min(
                    shapes[inst_id]["half_extents"]
                )
            assert err.max() < tol, (f, inst_id, err.max())


def test_ground_truth_geometry(scene, default_dir):
    gt = scene.ground_truth
    pts, inst = gt["points3d"].astype(np.float64), gt["points_instance"]
    T = scene.num_timesteps
    info = {d["id"]: d for d in json.loads((default_dir / "mogaf_gt/instances.json").read_text())["instances"]}
    poses = dict(zip(gt["object_pose_ids"].tolist(), gt["object_poses"]))
    for k in (1, 2):  # rigid: exactly rigid, and consistent with the poses
        p = pts[inst == k]
        assert max(_kabsch_residual(p[:, 0], p[:, t]) for t in range(T)) < 1e-5
        rel = poses[k][T - 1] @ np.linalg.inv(poses[k][0])
        np.testing.assert_allclose(p[:, 0] @ rel[:3, :3].T + rel[:3, 3], p[:, T - 1], atol=1e-5)
    cloth = pts[inst == 3]
    assert max(_kabsch_residual(cloth[:, 0], cloth[:, t]) for t in range(T)) > 0.02
    # sphere: points at the radius around the pose centre; centre on a parabola (no bounce by default)
    centre = poses[2][:, :3, 3]
    r = info[2]["shape"]["radius"]
    np.testing.assert_allclose(np.linalg.norm(pts[inst == 2] - centre[None], axis=2), r, atol=1e-5)
    p = resolve_params({})
    dt = 1.0 / p["fps"]
    acc = np.diff(centre[:, 2], 2) / dt**2
    np.testing.assert_allclose(acc, -p["gravity"] * p["speed"] ** 2, rtol=1e-6)
    np.testing.assert_allclose(np.diff(centre[:, :2], 2, axis=0), 0, atol=1e-9)
    assert centre[:, 2].min() >= r - 1e-9
    # box: its 8 corners stay above the ground and in front of the wall, and it moves and spins
    half = np.array(info[1]["shape"]["half_extents"])
    corners = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)]) * half
    world = np.einsum("tij,nj->tni", poses[1][:, :3, :3], corners) + poses[1][:, None, :3, 3]
    assert world[..., 2].min() > 0 and world[..., 1].max() < 2.6
    assert np.linalg.norm(poses[1][-1, :3, 3] - poses[1][0, :3, 3]) > 0.3
    angle = np.degrees(np.arccos((np.trace(poses[1][-1, :3, :3] @ poses[1][0, :3, :3].T) - 1) / 2))
    assert 45 < angle < 180


def test_cameras_train_moves_test_fixed(scene):
    from mogaf.camera import camera_centers

    centres = camera_centers(scene.w2c)
    train = centres[scene.camera_id == 0]
    assert 0.3 < np.linalg.norm(train[-1] - train[0]) < 1.5
    for c in (1, 2):
        test = centres[scene.camera_id == c]
        assert np.allclose(test, test[0])
        assert np.linalg.norm(train - test[0], axis=1).min() > 0.5
        # 15-30 degrees away from the train camera's mean viewing direction, around the look-at point
        look = np.array(scene.meta["lookat"])
        a, b = train.mean(0) - look, test[0] - look
        angle = np.degrees(np.arccos(a @ b / np.linalg.norm(a) / np.linalg.norm(b)))
        assert 12 < angle < 32, angle


# ---------------------------------------------------------------- determinism + atomicity
def test_same_seed_identical_files_other_seed_differs(tmp_path):
    # frames rendered on threads give the same files
    a = generate_scene(tmp_path / "a", {**SMALL, "nonrigid": "arm", "num_extra_objects": 1})
    b = generate_scene(tmp_path / "b", {**SMALL, "nonrigid": "arm", "num_extra_objects": 1}, threads=3)
    c = generate_scene(tmp_path / "c", {**SMALL, "nonrigid": "arm", "num_extra_objects": 1, "seed": 1})
    da, db, dc = _tree_digest(a), _tree_digest(b), _tree_digest(c)
    assert da == db
    assert set(da) == set(dc)
    assert da["rgb/1x/0_00003.png"] != dc["rgb/1x/0_00003.png"]
    assert da["mogaf_gt/points3d.npy"] != dc["mogaf_gt/points3d.npy"]
    names = [d["name"] for d in json.loads((a / "mogaf_gt/instances.json").read_text())["instances"]]
    assert names[:3] == ["box", "sphere", "arm"] and len(names) == 4


def test_generation_is_atomic(tmp_path, monkeypatch):
    import mogaf.synth.generate as gen

    out = generate_scene(tmp_path / "scene", SMALL)
    before = _tree_digest(out)

    def boom(*args, **kwargs):
        raise RuntimeError("killed")

    monkeypatch.setattr(gen, "_render_all", boom)
    with pytest.raises(RuntimeError):
        generate_scene(out, {**SMALL, "seed": 5})
    assert _tree_digest(out) == before, "a failed run leaves the previous scene untouched"
    assert [p.name for p in tmp_path.iterdir()] == ["scene"], "and no temporary folder"
    with pytest.raises(MogafError):
        generate_scene(tmp_path / "other", {"speed": "fast"})
    assert not (tmp_path / "other").exists()
    # a frame that fails on a thread (a full disk at the fifth PNG): its one-line error, no folder
    monkeypatch.undo()
    real_write_png = gen._write_png
    written = []

    def full_disk(path, img):
        written.append(path)
        if len(written) == 5:
            raise OSError(28, "No space left on device")
        return real_write_png(path, img)

    monkeypatch.setattr(gen, "_write_png", full_disk)
    with pytest.raises(MogafError, match="no space left on device"):
        generate_scene(tmp_path / "threads", SMALL, threads=2)
    assert [p.name for p in tmp_path.iterdir()] == ["scene"]


def test_reader_reports_missing_scene(tmp_path):
    from mogaf.datasets import read_scene

    with pytest.raises(MogafError, match="synthesize"):
        read_scene("synthetic", tmp_path / "absent", dataset="synthetic", scene="default", options={"scale": 1})


# ---------------------------------------------------------------- the forecasting presets
def test_articulated_preset_is_a_still_body_with_one_moving_part():
    world = build_world(resolve_params({"preset": "articulated"}))
    assert check_world(world) is None
    (chest,) = world.objects
    assert chest.kind == "articulated" and not chest.rigid
    material = chest.sample_material(np.random.default_rng(0), 400)
    track = np.stack([chest.points(material, float(tau)) for tau in world.taus], axis=1)  # (P, T, 3)
    reach = np.linalg.norm(track - track[:, :1], axis=-1).max(axis=1)
    body, lid = material[:, 0] == 0, material[:, 0] == 1
    assert body.sum() > lid.sum() > 0, "most of the surface is the still body"
    assert reach[body].max() == 0.0
    assert reach[lid].max() > 0.2, "the lid swings (metres)"
    # the lid itself moves as one rigid body
    assert _kabsch_residual(track[lid, 0], track[lid, -1]) < 1e-9


def test_articulated_scene_ships_no_instance_masks(tmp_path):
    from mogaf.datasets import read_scene

    root = generate_scene(tmp_path / "art", {**SMALL, "preset": "articulated", "num_frames": 8})
    scene = read_scene("synthetic", root, dataset="synthetic", scene="articulated", options={"scale": 1})
    assert list(scene.instances.names) == ["foreground"], "the reader keeps the foreground mask alone"
    assert set(np.unique(scene.instance_mask).tolist()) <= {0, 1}
    assert scene.ground_truth["points3d"].shape[1] == 8, "ground truth stays for scoring"
    # ...and so do the pieces that move as one, per pixel and per GT point
    assert scene.segments.names == ["chest/body", "chest/lid"] and len(set(scene.segments.instance.tolist())) == 1
    label = scene.segments.label
    assert set(np.unique(label).tolist()) == {0, 1, 2}
    np.testing.assert_array_equal(label > 0, scene.instance_mask > 0)
    part = np.load(root / "mogaf_gt/points_part.npy")
    track = scene.ground_truth["points3d"]
    reach = np.linalg.norm(track - track[:, :1], axis=-1).max(axis=1)
    assert part.dtype == np.uint8 and reach[part == 0].max() < 1e-6 < reach[part == 1].min()
    entry = json.loads((root / "mogaf_gt/instances.json").read_text())["instances"][0]
    assert entry["parts"] == ["body", "lid"]
    # a part index the instance does not list is one line naming the file
    bad = root / "mogaf_gt/part/1x/0_00003.png"
    cv2.imwrite(str(bad), np.full_like(cv2.imread(str(bad), cv2.IMREAD_UNCHANGED), 2))
    with pytest.raises(MogafError, match=r"0_00003\.png: part indices of instance \d+ go past its 2 listed part"):
        read_scene("synthetic", root, dataset="synthetic", scene="articulated", options={"scale": 1})


def test_bounce_preset_bounces_after_either_split():
    world = build_world(resolve_params({"preset": "bounce"}))
    assert check_world(world) is None
    frames = [b * world.params.fps for b in world.info["sphere_bounce_times"]]
    last = world.params.num_frames - 1
    assert len(frames) >= 1 and 0.8 * last < frames[0] < last, frames


def _pair(world):
    """The stuck pair's two spheres of `world`, by name."""
    by_name = {o.name: o for o in world.objects}
    return by_name["sphere"], by_name["sphere_2"]


def test_stuck_spheres_meet_at_the_stick_time_and_move_on_as_one_body():
    world = build_world(resolve_params({"stick_time": 0.7, "num_frames": 60}))
    assert check_world(world) is None
    a, b = _pair(world)
    taus = world.taus
    contact = 0.7 * taus[-1]
    assert world.info["stick_time"] == pytest.approx(0.7 * world.times[-1])
    assert world.info["sphere_bounce_times"] == []  # the pair's sphere is not thrown
    centres = np.array([[o.centre_fn(float(t)) for t in taus] for o in (a, b)])  # (2, T, 3)
    gap = np.linalg.norm(centres[0] - centres[1], axis=-1) - (a.r + b.r)
    before, after = taus < contact, taus >= contact
    assert np.all(gap[before] > 0) and np.all(np.diff(gap[before]) < 0)  # they close in, apart until the contact
    np.testing.assert_allclose(gap[after], 0.0, atol=1e-12)  # then touch, never overlapping
    # From the contact on both move with one velocity, which keeps the pair's momentum (masses ~ r^3).
    step = np.diff(taus)[0]
    v = np.diff(centres, axis=1) / step  # (2, T-1, 3)
    first, last = v[:, 0], v[:, -1]
    np.testing.assert_allclose(last[0], last[1], atol=1e-12)
    mass = np.array([a.r, b.r]) ** 3
    np.testing.assert_allclose(mass @ first, mass.sum() * last[0], atol=1e-12)
    assert np.dot(first[0], last[0]) > 0 and np.linalg.norm(last[0]) < np.linalg.norm(first[0])  # slowed, not turned
    # They spin until the contact and hold their orientation after it.
    for o in (a, b):
        rots = np.array([o.rotation(float(t)) for t in taus])
        assert not np.allclose(rots[0], rots[np.flatnonzero(before)[-1]])
        np.testing.assert_array_equal(rots[after], np.broadcast_to(rots[np.flatnonzero(after)[0]], rots[after].shape))


def test_a_stuck_pair_is_the_only_contact_the_checks_allow():
    world = build_world(resolve_params({"stick_time": 0.7, "num_extra_objects": 2}))
    a, b = _pair(world)
    assert (a.inst, b.inst) == (2, 4) and [o.inst for o in world.objects[-2:]] == [5, 6]  # extras after the pair
    assert check_world(world) is None
    box = world.objects[0]
    box_path = box.centre_fn
    box.centre_fn = b.centre_fn  # another object on the second sphere's path is still a collision
    assert "box and sphere_2 may collide" in check_world(world)
    box.centre_fn = box_path
    a.touches = b.touches = frozenset()  # without the allowance the pair itself is one
    assert "sphere and sphere_2 may collide" in check_world(world)


def test_a_stuck_pair_needs_the_sphere_and_time_to_meet():
    with pytest.raises(MogafError, match="stick_time"):
        resolve_params({"stick_time": 1.0})
    with pytest.raises(MogafError, match="'stick_time' needs rigid_objects"):
        build_world(resolve_params({"stick_time": 0.7, "rigid_objects": False}))
    with pytest.raises(MogafError, match=r"'stick_time' \(0.7\) must come before motion_stop \(0.5\)"):
        build_world(resolve_params({"stick_time": 0.7, "motion_stop": 0.5}))
    with pytest.raises(MogafError, match=r"'stick_bodies' \(blobs\) needs a stick_time above 0"):
        build_world(resolve_params({"stick_bodies": "blobs"}))
    with pytest.raises(MogafError, match="sphere.* leaves the view .*; raise stick_time"):
        build_world(resolve_params({"stick_time": 0.1}))  # a fast approach starts outside the view


def _random_rotation(rng) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def test_an_ellipsoid_of_a_scaled_rotation_is_that_sphere():
    from mogaf.synth.primitives import Ellipsoid, Sphere
    from mogaf.synth.textures import SphereTexture

    rng = np.random.default_rng(0)
    texture = SphereTexture(rng, 0.3)
    R = _random_rotation(rng)
    centre, r = np.array([0.2, 1.5, 0.4]), 0.3
    sphere, ellipsoid = Sphere(R, centre, r, texture, 2), Ellipsoid(r * R, centre, texture, 2)
    o = np.zeros(3)
    d = centre + rng.uniform(-0.5, 0.5, (400, 3))  # rays towards and past the ball
    t_s, t_e = sphere.intersect(o, d), ellipsoid.intersect(o, d)
    hit = np.isfinite(t_s)
    assert 50 < hit.sum() < 400 and np.array_equal(hit, np.isfinite(t_e))
    np.testing.assert_allclose(t_e[hit], t_s[hit], rtol=1e-12)
    p = o + t_s[hit, None] * d[hit]
    for got, want in zip(ellipsoid.shade(p, d[hit]), sphere.shade(p, d[hit])):
        np.testing.assert_allclose(got, want, atol=1e-12)
    assert ellipsoid.radius == pytest.approx(r)


def test_an_ellipsoid_of_any_map_is_hit_on_its_surface_with_its_outward_normal():
    from mogaf.synth.primitives import Ellipsoid
    from mogaf.synth.textures import SphereTexture

    rng = np.random.default_rng(3)
    A = rng.normal(size=(3, 3)) * 0.3  # neither symmetric nor a scaled rotation
    centre = np.array([0.1, 2.0, 0.5])
    ellipsoid = Ellipsoid(A, centre, SphereTexture(rng, 0.6), 2)
    A_inv = np.linalg.inv(A)

    def level(x):  # 1 on the surface, below inside
        return np.sum(((x - centre) @ A_inv.T) ** 2, axis=-1)

    o = np.zeros(3)
    d = centre + rng.uniform(-1.0, 1.0, (600, 3))
    t = ellipsoid.intersect(o, d)
    hit = np.isfinite(t)
    assert 50 < hit.sum() < 600
    p = o + t[hit, None] * d[hit]
    np.testing.assert_allclose(level(p), 1.0, atol=1e-9)
    # the first crossing: the ray's points a little before the hit are outside
    assert np.all(level(o + (t[hit, None] * (1 - 1e-6)) * d[hit]) > 1.0)
    _, normal = ellipsoid.shade(p, d[hit])
    eps = 1e-6
    grad = np.stack([(level(p + eps * e) - level(p - eps * e)) / (2 * eps) for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(normal, grad / np.linalg.norm(grad, axis=1, keepdims=True), atol=1e-6)
    # the bounding sphere and the box of extent points enclose the surface, and touch it
    u = rng.normal(size=(20000, 3))
    surface = centre + (u / np.linalg.norm(u, axis=1, keepdims=True)) @ A.T
    reach = np.linalg.norm(surface - centre, axis=1).max()
    assert reach <= ellipsoid.radius + 1e-12 and reach > 0.99 * ellipsoid.radius


def test_merging_blobs_meet_squash_into_one_another_and_move_on_as_one():
    from mogaf.synth.world import MERGE_OVERLAP, MERGE_SQUASH

    world = build_world(resolve_params({"stick_time": 0.7, "num_frames": 60, "stick_bodies": "blobs"}))
    assert check_world(world) is None
    by_name = {o.name: o for o in world.objects}
    a, b = by_name["blob"], by_name["blob_2"]
    assert (a.inst, b.inst, a.rigid, b.rigid) == (2, 4, False, False) and "sphere" not in by_name
    path = a.path
    tc, n = path.tau_contact, path.n
    assert tc == pytest.approx(0.7 * world.taus[-1])
    contact_gap = a.r + b.r

    def gap(tau):
        return float(np.linalg.norm(path.centre(1, tau) - path.centre(0, tau)))

    assert gap(0.0) > contact_gap and gap(tc) == pytest.approx(contact_gap)  # the surfaces meet at the contact
    end = tc + path.duration
    assert gap(end) == pytest.approx((1 - MERGE_OVERLAP) * contact_gap) == gap(end + 0.3)  # nearer, then held
    # velocities are continuous at the contact; the centre of mass keeps the momentum-weighted velocity
    h = 1e-6
    mass = np.array([a.r, b.r]) ** 3
    for body in (0, 1):
        before = (path.centre(body, tc) - path.centre(body, tc - h)) / h
        after = (path.centre(body, tc + h) - path.centre(body, tc)) / h
        np.testing.assert_allclose(before, after, atol=1e-6)

    def mass_centre(tau):
        return (mass[0] * path.centre(0, tau) + mass[1] * path.centre(1, tau)) / mass.sum()

    v_before = (
        (path.centre(0, tc - 2 * h) - path.centre(0, tc - 3 * h)) / h,
        (path.centre(1, tc - 2 * h) - path.centre(1, tc - 3 * h)) / h,
    )
    momentum = (mass[0] * v_before[0] + mass[1] * v_before[1]) / mass.sum()
    for tau in (tc + 0.3 * path.duration, end, end + 0.2):
        np.testing.assert_allclose(mass_centre(tau) - mass_centre(tc), momentum * (tau - tc), atol=1e-9)
    # the shape: a ball before the contact, squashed along the line (volume kept) by its end, spinning no more
    material = np.random.default_rng(1).normal(size=(2000, 3))
    material /= np.linalg.norm(material, axis=1, keepdims=True)
    for blob in (a, b):
        before, merged = blob.map(0.5 * tc), blob.map(end)
        np.testing.assert_allclose(np.linalg.svd(before, compute_uv=False), blob.r, rtol=1e-12)
        assert np.linalg.det(merged) == pytest.approx(blob.r**3)
        assert np.linalg.norm(merged.T @ n) == pytest.approx((1 - MERGE_SQUASH) * blob.r)  # half-extent along n
        np.testing.assert_allclose(blob.map(end + 0.2), merged, atol=1e-12)

        def unsquashed(tau, blob=blob):  # the map without the squash: the blob's orientation
            k = 1 - MERGE_SQUASH * path.merged(tau)
            stretch = np.eye(3) / np.sqrt(k) + (k - 1 / np.sqrt(k)) * np.outer(n, n)
            return np.linalg.solve(stretch, blob.map(tau))

        assert not np.allclose(unsquashed(tc - 0.05), unsquashed(tc))  # it spins up to the contact
        for tau in (tc + 0.2 * path.duration, end):
            np.testing.assert_allclose(unsquashed(tau), unsquashed(tc), atol=1e-12)  # and not after it
        # ground-truth points lie on the rendered surface, inside the box of extent points
        surface = blob.primitives(end)[0]
        points = blob.points(material, end)
        np.testing.assert_allclose(np.linalg.norm((points - surface.c) @ surface.A_inv.T, axis=1), 1.0, atol=1e-12)
        box = blob.extent_points(end)
        lo, hi = box.min(axis=0), box.max(axis=0)
        assert np.all(points >= lo - 1e-12) and np.all(points <= hi + 1e-12)
        np.testing.assert_allclose(points.min(axis=0), lo, atol=0.01)
        np.testing.assert_allclose(points.max(axis=0), hi, atol=0.01)
