"""The priors stage on tiny scenes: observed frames only, sources and leave-out rules."""

from __future__ import annotations

import os

import h5py
import numpy as np
import pytest

from mogaf.artefact import read_artefact
from mogaf.errors import MogafError
from mogaf.priors import DEFAULT_PARAMS
from mogaf.priors.stage import build_priors, run_priors_stage
from mogaf.scene import SPLIT_CODES, Instances, Scene, save_scene
from mogaf.split import split_scene, write_split
from support.moving_squares import moving_squares

T, H, W = 12, 64, 80
RATIO = 0.5  # 6 observed steps
T_OBS = 6
SQUARES = [(8.0, 10.0, 1.5, 0.3, 22), (50.0, 36.0, -0.4, -1.4, 20)]
FAST = {"grid_stride": 4, "num_query_frames": 3, "min_track_length": 3}


def _pose(tx: float) -> np.ndarray:
    w2c = np.eye(4)
    w2c[0, 3] = tx
    return w2c


def make_scene(
    layout: str = "iphone",
    *,
    depth: bool = True,
    instances: bool = False,
    shipped_tracks: bool = False,
    shipped_disparity: bool = False,
    gt_tracks: bool = False,
    som_foreground: bool = False,
) -> tuple[Scene, np.ndarray]:
    rng = np.random.default_rng(3)
    frames, alphas, _ = moving_squares(rng, T, H, W, SQUARES)
    K = np.array([[60.0, 0, W / 2], [0, 60.0, H / 2], [0, 0, 1]])
    if layout == "iphone":
        # Train camera 0 at every step, held-out camera 1 at every step.
        t_idx = np.concatenate([np.arange(T), np.arange(T)])
        cam = np.concatenate([np.zeros(T), np.ones(T)]).astype(np.int64)
        split = np.concatenate([np.full(T, SPLIT_CODES["train"]), np.full(T, SPLIT_CODES["val"])])
        images = np.concatenate([frames, frames[:, ::-1]])
        masks = np.concatenate([alphas, alphas[:, :, ::-1]], axis=1)
    else:
        # D-NeRF: train frames at every step, test frames at every step, every frame its own camera.
        t_idx = np.concatenate([np.arange(T), np.arange(T)])
        cam = np.arange(2 * T)
        split = np.concatenate([np.full(T, SPLIT_CODES["train"]), np.full(T, SPLIT_CODES["test"])])
        images = np.concatenate([frames, frames[:, ::-1]])
        masks = np.concatenate([alphas, alphas[:, :, ::-1]], axis=1)
    F = len(t_idx)
    inst = np.zeros((F, H, W), np.int32)
    for k in range(len(SQUARES)):
        inst[masks[k] > 0.5] = k + 1
    scene = Scene(
        dataset="toy",
        name="squares",
        layout=layout,
        frame_names=[f"f{i:03d}" for i in range(F)],
        images=images.astype(np.uint8),
        K=np.repeat(K[None], F, 0),
        w2c=np.stack([_pose(float(c)) for c in cam]),
        time=t_idx / (T - 1.0),
        time_index=t_idx.astype(np.int64),
        num_timesteps=T,
        camera_id=cam.astype(np.int64),
        source_split=split.astype(np.int8),
        meta={"background": [0.0, 0.0, 0.0]},
    )
    if depth:
        scene.depth = (2.0 + 0.1 * rng.random((F, H, W))).astype(np.float32)
    if instances:
        scene.instance_mask = inst
        scene.instances = Instances(ids=[1, 2], names=["box", "cloth"], rigid=[1, 0])
    if som_foreground:
        # As the iPhone reader stores Shape-of-Motion's track_anything masks.
        scene.instance_mask = (inst > 0).astype(np.int32)
        scene.instances = Instances(ids=[1], names=["foreground"], rigid=[1])
    if shipped_disparity:
        # The iPhone reader's layout: rows that have a map (here train frames but the last two).
        rows = np.arange(T - 2)
        scene.shipped["disparity"] = {
            "frame": rows,
            "time_index": t_idx[rows],
            "values": (0.5 + 0.1 * rng.random((len(rows), H, W))).astype(np.float32),
        }
    P = 40
    track_xy = rng.uniform(5, 60, (P, T, 2)).astype(np.float32)
    track_vis = rng.random((P, T)) > 0.2
    if shipped_tracks:
        # The iPhone reader's layout of SoM's TAPIR tracks: 8 points per query frame (every 2nd train frame).
        queries = np.arange(0, T, 2)
        vals = np.zeros((8 * len(queries), T, 4), np.float32)
        vals[..., :2] = rng.uniform(5, 60, vals.shape[:2] + (2,))
        vals[..., 2] = rng.normal(-2.0, 3.0, vals.shape[:2])
        vals[..., 3] = rng.normal(-2.0, 1.0, vals.shape[:2])
        scene.shipped["tracks_2d"] = {
            "query_frame": queries,
            "query_time_index": t_idx[queries],
            "target_frame": np.arange(T),
            "target_time_index": t_idx[:T],
            "offsets": np.arange(0, 8 * len(queries) + 1, 8),
            "values": vals,
        }
        scene.shipped["keypoints"] = {
            "frame": np.arange(T),
            "time_index": t_idx[:T],
            "values": rng.random((T, 3, 3)).astype(np.float32),
        }
    if gt_tracks:
        scene.ground_truth = {
            "tracks2d": track_xy,
            "visible": track_vis.astype(np.uint8),
            "points3d": rng.random((P, T, 3)).astype(np.float32),
            "points_instance": (np.arange(P) % 2 + 1).astype(np.int64),
        }
    return scene, t_idx


def write_inputs(tmp_path, scene: Scene) -> tuple[str, str]:
    scene_h5 = tmp_path / "scene.h5"
    split_h5 = tmp_path / "split.h5"
    save_scene(scene_h5, scene, config_digest="test")
    write_split(split_h5, split_scene(scene_h5, RATIO))
    return str(scene_h5), str(split_h5)


def _poison_disparity(fh, rng, bad: np.ndarray) -> None:
    """Shipped disparity rows of the frames in `bad`."""
    if "shipped/disparity" not in fh:
        return
    ds = fh["shipped/disparity/values"]
    for i, r in enumerate(fh["shipped/disparity/frame"][()]):
        if r in bad:
            ds[i] = rng.uniform(0.1, 50.0, ds.shape[1:])


def _poison_shipped_tracks(fh, rng) -> None:
    """Shipped 2D tracks: future targets, and every target of a future query."""
    if "shipped/tracks_2d" not in fh:
        return
    g = fh["shipped/tracks_2d"]
    ds, off = g["values"], g["offsets"][()]
    ds[:, T_OBS:] = rng.uniform(-5, 60, ds[:, T_OBS:].shape)
    for q, qt in enumerate(g["query_time_index"][()]):
        if qt >= T_OBS:
            ds[off[q] : off[q + 1]] = rng.uniform(-5, 60, ds[off[q] : off[q + 1]].shape)


def _poison_frames(fh, rng, bad: np.ndarray) -> None:
    """Images, depth and instance masks of the frames in `bad`."""
    for key in ("frames/images", "frames/depth", "frames/instance_mask"):
        if key not in fh:
            continue
        ds = fh[key]
        for r in bad:
            if ds.dtype == np.uint8:
                ds[r] = rng.integers(0, 256, ds.shape[1:], dtype=np.uint8)
            elif ds.dtype.kind == "i":
                ds[r] = rng.integers(0, 3, ds.shape[1:])
            else:
                ds[r] = rng.uniform(0.1, 50.0, ds.shape[1:])


def _poison_ground_truth(fh, rng) -> None:
    """Future steps of the ground-truth tracks and visibility."""
    for key in ("ground_truth/tracks2d",):
        if key in fh:
            ds = fh[key]
            ds[:, T_OBS:] = rng.uniform(0, 60, ds[:, T_OBS:].shape)
    for key in ("ground_truth/visible",):
        if key in fh:
            ds = fh[key]
            ds[:, T_OBS:] = rng.integers(0, 2, ds[:, T_OBS:].shape)


def poison_future(scene_h5: str, t_idx: np.ndarray, train_code_rows: np.ndarray) -> None:
    """Overwrite everything a stage must not see: future frames, future GT/shipped steps, held-out frames."""
    rng = np.random.default_rng(99)
    bad = np.flatnonzero((t_idx >= T_OBS) | ~train_code_rows)
    with h5py.File(scene_h5, "r+", locking=False) as fh:
        _poison_disparity(fh, rng, bad)
        _poison_shipped_tracks(fh, rng)
        _poison_frames(fh, rng, bad)
        _poison_ground_truth(fh, rng)


def assert_same(a, b) -> None:
    da, db = a.to_data(), b.to_data()

    def flat(d, prefix=""):
        out = {}
        for k, v in d.items():
            if isinstance(v, dict):
                out.update(flat(v, f"{prefix}{k}/"))
            else:
                out[prefix + k] = v
        return out

    fa, fb = flat(da), flat(db)
    assert fa.keys() == fb.keys()
    for k in fa:
        assert np.array_equal(np.asarray(fa[k]), np.asarray(fb[k])), k
    aa, ab = a.attrs(), b.attrs()
    for k in [k for k in aa if k.endswith("seconds")]:
        aa.pop(k), ab.pop(k, None)
    assert aa == ab


@pytest.mark.parametrize("kind", ["computed", "ground_truth", "shipped"])
def test_priors_depend_only_on_observed_frames(tmp_path, kind):
    if kind == "computed":
        scene, t_idx = make_scene()
    elif kind == "ground_truth":
        scene, t_idx = make_scene(instances=True, gt_tracks=True, shipped_disparity=True)
    else:
        scene, t_idx = make_scene(shipped_tracks=True, shipped_disparity=True, som_foreground=True)
    scene_h5, split_h5 = write_inputs(tmp_path, scene)
    before = build_priors(scene_h5, split_h5, FAST)
    poison_future(scene_h5, t_idx, scene.source_split == SPLIT_CODES["train"])
    after = build_priors(scene_h5, split_h5, FAST)
    assert_same(before, after)
    assert len(before.frame_ids) == T_OBS and np.array_equal(before.timesteps, np.arange(T_OBS))
    assert before.tracks.num_tracks > 0
    if kind == "computed":
        assert before.sources["tracks"].startswith("optical_flow")
        assert before.sources["masks"].startswith("motion_segmentation")
        assert before.sources["instances"].startswith("track_clustering")
    elif kind == "ground_truth":
        assert before.sources == {
            "depth": "shipped/disparity",
            "tracks": "ground_truth",
            "masks": "dataset_instance_masks",
            "instances": "dataset_instance_masks",
        }
        assert before.depth_kind == "disparity"
    else:
        assert before.sources["tracks"] == "shipped" and before.sources["masks"] == "dataset_foreground_mask"
        assert before.sources["instances"].startswith("track_clustering")


def test_stage_writes_the_schema(tmp_path):
    scene, _ = make_scene()
    scene_h5, split_h5 = write_inputs(tmp_path, scene)
    out = run_priors_stage(scene_h5, split_h5, tmp_path / "r" / "priors.h5", FAST)
    art = read_artefact(out, "priors")
    F = T_OBS
    assert art["frame_ids"].dtype == np.int64 and np.array_equal(art["frame_ids"], np.arange(F))
    assert np.array_equal(art["timesteps"], np.arange(F))
    fg = art["masks/foreground"]
    assert fg.shape == (F, H, W) and fg.dtype == np.uint8 and set(np.unique(fg)) <= {0, 1}
    inst = art["masks/instance"]
    assert inst.dtype == np.int32 and inst.shape == (F, H, W)
    ids = art["instances/ids"]
    assert set(np.unique(inst)) <= {0, *ids.tolist()}
    assert np.all(inst[fg == 0] == 0)
    assert art["instances/rigid"].dtype == np.int8 and np.all(art["instances/rigid"] == -1)
    assert art["instances/rigid_source"] == ["unknown"] * len(ids)
    assert len(art["instances/names"]) == len(ids)
    assert art["depth/values"].shape == (F, H, W) and art["depth/values"].dtype == np.float32
    assert art["depth/valid"].dtype == np.uint8 and art["depth/valid"].all()
    P = art["tracks/xy"].shape[0]
    assert P > 0 and art["tracks/xy"].shape == (P, F, 2) and art["tracks/xy"].dtype == np.float32
    assert art["tracks/visible"].shape == (P, F) and art["tracks/visible"].dtype == np.uint8
    assert art["tracks/query_index"].dtype == np.int64 and art["tracks/query_index"].max() < F
    assert art["tracks/confidence"].shape == (P, F)
    a = art.attrs
    assert a["layout"] == "iphone" and a["depth_kind"] == "depth"
    assert set(a["sources"]) == {"masks", "instances", "depth", "tracks"}
    assert a["track_count"] == P and a["track_mean_length"] >= FAST["min_track_length"]
    assert 0 <= a["track_fb_error_median_px"] <= a["track_fb_error_p95_px"]
    # Two squares moving differently: two instances, each mostly one square.
    assert len(ids) == 2
    _, alphas, _ = moving_squares(np.random.default_rng(3), T, H, W, SQUARES)  # make_scene's squares
    owners = []
    for k in (0, 1):
        only_k = (alphas[k, :F] > 0.99) & (alphas[1 - k, :F] < 0.01)
        labels = inst[only_k]
        owners.append(int(np.bincount(labels).argmax()))
        assert owners[-1] != 0 and (labels == owners[-1]).mean() > 0.9, k
    assert owners[0] != owners[1]


def test_dnerf_gets_no_depth_and_no_tracks(tmp_path):
    scene, _ = make_scene("dnerf", depth=True, instances=True)
    scene_h5, split_h5 = write_inputs(tmp_path, scene)
    res = build_priors(scene_h5, split_h5, FAST)
    data = res.to_data()
    assert "depth" not in data and "tracks" not in data and res.depth_kind == "none"
    assert "teleports" in res.sources["tracks"] and res.sources["depth"].startswith("none")
    assert res.sources["masks"] == "dataset_instance_masks"
    assert data["instances"]["rigid"].tolist() == [1, 0]
    assert data["instances"]["rigid_source"] == ["dataset", "dataset"]
    assert data["instances"]["names"] == ["box", "cloth"]


def test_dnerf_without_masks_uses_background_colour(tmp_path):
    scene, _ = make_scene("dnerf", depth=False)
    scene_h5, split_h5 = write_inputs(tmp_path, scene)
    res = build_priors(scene_h5, split_h5, FAST)
    assert res.sources["masks"] == "background_colour" and res.sources["instances"] == "none"
    assert "instance" not in res.to_data()["masks"]


def test_dnerf_alpha_is_the_foreground(tmp_path):
    scene, _ = make_scene("dnerf", depth=False)
    alpha = np.zeros((2 * T, H, W), np.uint8)
    alpha[:, 10:30, 20:50] = 255
    scene.alpha = alpha
    scene_h5, split_h5 = write_inputs(tmp_path, scene)
    res = build_priors(scene_h5, split_h5, FAST)
    assert res.sources["masks"] == "alpha"
    assert np.array_equal(res.foreground, (alpha[:T_OBS] > 127).astype(np.uint8))


def test_shipped_tracks_are_used_not_computed(tmp_path):
    from scipy.special import expit

    scene, _ = make_scene(shipped_tracks=True)
    scene_h5, split_h5 = write_inputs(tmp_path, scene)
    res = build_priors(scene_h5, split_h5, {**FAST, "min_track_length": 1})
    assert res.sources["tracks"] == "shipped"
    assert res.tracks.fb_error is None and "fb_error" not in res.to_data()["tracks"]
    assert res.track_stats["fb_error_median_px"] == -1.0
    assert res.shipped_ignored == ["shipped/keypoints"]
    g = scene.shipped["tracks_2d"]
    # Queries on future frames are dropped; the others keep their observed columns.
    q_obs = np.flatnonzero(g["query_time_index"] < T_OBS)
    rows = np.concatenate([np.arange(g["offsets"][q], g["offsets"][q + 1]) for q in q_obs])
    assert res.tracks.num_tracks == len(rows)
    vals = g["values"][rows, :T_OBS]
    vis = expit(-vals[..., 2]) * expit(-vals[..., 3]) > 0.5
    qi = np.repeat(g["query_frame"][q_obs], 8)
    vis[np.arange(len(rows)), qi] = True
    assert np.array_equal(res.tracks.query_index, qi)
    assert np.array_equal(res.tracks.visible, vis)
    assert np.allclose(res.tracks.xy[vis], vals[..., :2][vis])
    assert np.all(res.tracks.confidence[~vis] == 0)


def test_shipped_disparity_is_used_with_missing_frames_invalid(tmp_path):
    scene, _ = make_scene(shipped_disparity=True)
    scene_h5, split_h5 = write_inputs(tmp_path, scene)
    res = build_priors(scene_h5, split_h5, FAST)
    assert res.sources["depth"] == "shipped/disparity" and res.depth_kind == "disparity"
    assert np.allclose(res.depth, scene.shipped["disparity"]["values"][:T_OBS])
    res2 = build_priors(scene_h5, split_h5, {**FAST, "depth_sources": ["scene", "shipped"]})
    assert res2.sources["depth"] == "scene_depth" and res2.depth_kind == "depth"


def test_single_foreground_mask_is_split_by_clustering(tmp_path):
    scene, _ = make_scene(som_foreground=True)
    fgm = scene.instance_mask[:T]
    scene_h5, split_h5 = write_inputs(tmp_path, scene)
    res = build_priors(scene_h5, split_h5, FAST)
    assert res.sources["masks"] == "dataset_foreground_mask"
    assert res.sources["instances"].startswith("track_clustering")
    assert len(res.instance_ids) == 2 and res.instance_rigid.tolist() == [1, 1]
    assert np.array_equal(res.foreground, fgm[:T_OBS].astype(np.uint8))
    res2 = build_priors(scene_h5, split_h5, {**FAST, "cluster_single_foreground": False})
    assert res2.sources["instances"] == "dataset_instance_masks" and res2.instance_names == ["foreground"]


def test_monocular_without_depth_fails_in_one_line(tmp_path):
    scene, _ = make_scene(depth=False)
    scene_h5, split_h5 = write_inputs(tmp_path, scene)
    out = tmp_path / "res" / "priors.h5"
    with pytest.raises(MogafError) as exc:
        run_priors_stage(scene_h5, split_h5, out, FAST)
    msg = str(exc.value)
    assert "\n" not in msg and "depth" in msg and "aligned_depth_anything_colmap" in msg and "scene.h5" in msg
    assert not out.exists()
    assert not out.parent.exists() or not os.listdir(out.parent)


def test_unknown_parameter_is_refused(tmp_path):
    with pytest.raises(MogafError, match="grid_strid"):
        build_priors("unused.h5", "unused.h5", {"grid_strid": 4})
    assert set(FAST) <= set(DEFAULT_PARAMS)


def test_iphone_reader_layout_end_to_end(tmp_path):
    """Shape-of-Motion files as the iPhone reader stores them (fake DyCheck scene)."""
    from mogaf.datasets import read_scene
    from support.fake_datasets import fake_iphone

    root = fake_iphone(tmp_path / "scene", num_times=8, full_size=(64, 48), track_points=3)
    scene = read_scene("iphone", root, dataset="fake", scene="s", options={"scale": 2})
    scene_h5, split_h5 = write_inputs(tmp_path, scene)
    res = build_priors(scene_h5, split_h5, {"min_track_length": 1})
    n_obs = 4  # 8 steps at ratio 0.5
    assert res.sources["depth"] == "shipped/disparity" and res.depth_kind == "disparity"
    assert res.sources["tracks"] == "shipped" and res.sources["masks"] == "dataset_foreground_mask"
    assert res.depth.shape == (n_obs, 24, 32) and res.depth_valid.all()
    # 3 points per observed query frame; fake track x = point + query index, y = target index (+0.5 centres).
    tr = res.tracks
    assert tr.num_tracks == 3 * n_obs and np.array_equal(tr.query_index, np.repeat(np.arange(n_obs), 3))
    assert np.allclose(tr.xy[..., 0], (np.arange(3)[None, :] + np.arange(n_obs)[:, None]).reshape(-1)[:, None] + 0.5)
    assert np.allclose(tr.xy[..., 1], np.arange(n_obs)[None, :] + 0.5)
    assert tr.visible.all()
    assert "shipped/keypoints" in res.shipped_ignored


def test_iphone_without_any_depth_names_the_files(tmp_path):
    from mogaf.datasets import read_scene
    from support.fake_datasets import fake_iphone

    root = fake_iphone(tmp_path / "scene", num_times=8, full_size=(64, 48), depth=False, som=False)
    scene = read_scene("iphone", root, dataset="fake", scene="s", options={"scale": 2})
    scene_h5, split_h5 = write_inputs(tmp_path, scene)
    with pytest.raises(MogafError) as exc:
        run_priors_stage(scene_h5, split_h5, tmp_path / "priors.h5", FAST)
    msg = str(exc.value)
    assert "\n" not in msg and "depth/2x/<frame>.npy" in msg and "aligned_depth_anything_colmap/2x/<frame>.npy" in msg
    assert not (tmp_path / "priors.h5").exists()
