"""Stage entries: groups.h5, its quality at held-out views (grouping_quality.h5),
the model's quality there (reconstruction_quality/*.h5) and rigid.h5."""

from __future__ import annotations

import dataclasses
import shutil

import h5py
import numpy as np
import pytest
from sklearn.metrics import adjusted_rand_score

from mogaf.artefact import read_artefact, write_artefact
from mogaf.errors import MogafError
from mogaf.grouping.core import Groups, has_rigid_groups
from mogaf.grouping.metrics import (
    adjusted_rand_index,
    assigned_iou,
    grouping_quality,
    largest_overlap,
    per_object_iou,
)
from mogaf.grouping.params import DEFAULT_PARAMS
from mogaf.grouping.quality import read_grouping_quality, run_grouping_quality_stage
from mogaf.grouping.stage import (
    load_groups,
    read_rigid_init,
    run_group_stage,
    run_rigid_init_stage,
    write_groups,
)
from mogaf.reconstruction_quality.stage import (
    read_per_frame,
    read_reconstruction_quality,
    run_reconstruction_quality_stage,
)
from mogaf.representation import save_model
from mogaf.scene import Instances, Scene, Segments, load_scene, load_segments, save_scene
from mogaf.split import read_split, split_scene, write_split
from support.toy_grouping import look_at, model_from_points, splat_instance_masks, two_object_scene

T_ALL, T_OBS, W, H = 16, 12, 64, 48


@pytest.fixture(scope="module")
def toy_files(tmp_path_factory):
    """scene.h5 / split.h5 / priors.h5 / recon.h5 of the two-object toy scene."""
    root = tmp_path_factory.mktemp("toy")
    sc = two_object_scene(T=T_ALL, width=W, height=H, seed=2)
    traj = sc.model.trajectory_means
    K = sc.frames.K[0]
    held_out = look_at(np.array([1.5, -3.5, 2.5]), np.zeros(3))
    images, Ks, w2cs, times, tidx, cams, splits, masks, names = [], [], [], [], [], [], [], [], []
    for t in range(T_ALL):
        for cam, w2c in ((0, sc.frames.w2c[t]), (1, held_out)):
            images.append(np.zeros((H, W, 3), np.uint8))
            Ks.append(K)
            w2cs.append(w2c)
            times.append(t / (T_ALL - 1))
            tidx.append(t)
            cams.append(cam)
            splits.append(cam)  # camera 0 = train, camera 1 = val (held out)
            masks.append(splat_instance_masks(traj[:, t], sc.labels, K, w2c, W, H, radius=1))
            names.append(f"{cam}_{t:03d}")
    scene = Scene(
        dataset="toy",
        name="two_objects",
        layout="iphone",
        frame_names=names,
        images=np.stack(images),
        K=np.stack(Ks),
        w2c=np.stack(w2cs),
        time=np.array(times),
        time_index=np.array(tidx),
        num_timesteps=T_ALL,
        camera_id=np.array(cams),
        source_split=np.array(splits, np.int8),
        instance_mask=np.stack(masks).astype(np.int32),
        instances=Instances(ids=[1, 2], names=["sphere", "box"], rigid=[1, -1]),
    )
    scene_h5 = save_scene(root / "scene.h5", scene, config_digest="test")
    split = split_scene(scene_h5, T_OBS / T_ALL)
    assert split.num_observed_timesteps == T_OBS
    split_h5 = write_split(root / "split.h5", split)
    obs = split.frame_ids["observed"]
    priors_h5 = write_artefact(
        root / "priors.h5",
        "priors",
        {
            "frame_ids": obs,
            "timesteps": scene.time_index[obs],
            "masks": {
                "instance": scene.instance_mask[obs],
                "foreground": (scene.instance_mask[obs] > 0).astype(np.uint8),
            },
            "instances": {
                "ids": np.array([1, 2]),
                "names": ["sphere", "box"],
                "rigid": np.array([1, -1], np.int8),
                "rigid_source": ["dataset", "unknown"],
            },
        },
        config_digest="test",
    )
    model = model_from_points(traj[:, :T_OBS], sc.labels, seed=2)
    recon_h5 = save_model(root / "recon.h5", "recon", model, config_digest="test")
    return {
        "root": root,
        "scene": scene_h5,
        "split": split_h5,
        "priors": priors_h5,
        "recon": recon_h5,
        "labels": sc.labels,
        "model": model,
    }


@pytest.mark.parametrize("method", ["ours", "gaga4d"])
def test_group_stage_writes_groups_h5(toy_files, method):
    out = toy_files["root"] / f"groups_{method}.h5"
    run_group_stage(toy_files["recon"], toy_files["priors"], toy_files["scene"], out, {"method": method})
    art = read_artefact(out, "group")
    K = int(art.attrs["num_groups"])
    assert art["group_id"].dtype == np.int64 and art["group_id"].shape == (len(toy_files["labels"]),)
    assert art["group_rigid"].dtype == np.int8 and art["group_rigid"].shape == (K,)
    assert art["group_static"].dtype == np.int8 and art["group_instance_id"].shape == (K,)
    assert len(art["group_names"]) == K and len(art["group_rigid_source"]) == K
    assert art.attrs["method"] == method and art.attrs["params"]["method"] == method
    g = load_groups(out)
    assert g.num_groups == K and g.method == method
    assert g.params["overlap_threshold"] == 0.1 and g.params["keyframe_stride"] == 5
    if method == "ours":
        assert adjusted_rand_score(toy_files["labels"], g.group_id) > 0.9
        assert g.names == ["sphere", "box"]
        # sphere: label from the dataset; box: unknown -> estimated (rigid motion).
        assert g.rigid_source == ["label", "estimated"] and list(g.rigid) == [1, 1]
        # quality at held-out views: its own stage, from the files the pipeline gives it
        quality_h5 = run_grouping_quality_stage(
            toy_files["recon"],
            out,
            toy_files["scene"],
            toy_files["split"],
            toy_files["root"] / "grouping_quality.h5",
            {"max_frames": 4},
        )
        q = read_grouping_quality(quality_h5)
        assert q["method"] == "ours" and q["num_groups"] == K
        assert q["ari"] > 0.6 and min(q["per_object_iou"]) > 0.6 and q["num_frames"] == 4
        assert q["object_ids"] == [1, 2]
        with h5py.File(quality_h5, "r+") as fh:  # an entry that disagrees with the objects the section names
            del fh["per_object_iou"]
            fh.create_dataset("per_object_iou", data=np.asarray(q["per_object_iou"][:1], np.float64), fletcher32=True)
        with pytest.raises(
            MogafError,
            match=r"grouping_quality\.h5: entry 'per_object_iou' has shape \(1,\), but 'quality' names 2 object",
        ):
            read_grouping_quality(quality_h5)
    assert "quality" not in art and "ari" not in art.attrs  # the group stage opens no held-out view
    assert has_rigid_groups(out) == bool(np.any(g.rigid == 1))


def test_reconstruction_quality_stage(toy_files):
    """PSNR of the model at evenly spaced held-out views at observed times,
    against -10 log10(MSE) computed here; a corrupted file is refused."""
    from mogaf.rendering import render_model

    out = run_reconstruction_quality_stage(
        toy_files["recon"],
        toy_files["scene"],
        toy_files["split"],
        toy_files["root"] / "reconstruction_quality" / "recon.h5",
        {"max_frames": 3},
    )
    q = read_reconstruction_quality(out)
    split = read_split(toy_files["split"])
    held_out = split.frame_ids["evaluation_observed"]
    assert held_out.size == T_OBS and q["num_frames"] == 3
    art = read_artefact(out, "reconstruction_quality")
    assert list(art["frame_ids"]) == list(held_out[[0, 6, 11]])  # evenly spaced over the 12 (5.5 rounds to 6)
    scene = load_scene(toy_files["scene"])
    psnrs = []
    for f in art["frame_ids"]:
        rendered = render_model(toy_files["model"], int(scene.time_index[f]), scene.K[f], scene.w2c[f], W, H)
        pred = np.clip(rendered.features[..., :3].detach().numpy().astype(np.float64), 0, 1)
        psnrs.append(-10 * np.log10(np.mean((pred - scene.images[f] / 255.0) ** 2)))
    assert list(art["timesteps"]) == [int(scene.time_index[f]) for f in art["frame_ids"]]
    assert list(read_per_frame(out)["camera_ids"]) == [int(scene.camera_id[f]) for f in art["frame_ids"]]
    assert q["heldout_observed"]["psnr"] == pytest.approx(np.mean(psnrs), rel=1e-9)
    assert set(q["heldout_observed"]) == {"psnr", "ssim", "mpsnr", "mssim"}  # iPhone layout: masked ones too
    # it reads only the held-out views at observed times: noise in every other frame changes nothing
    poisoned = toy_files["root"] / "poisoned_scene.h5"
    shutil.copyfile(toy_files["scene"], poisoned)
    with h5py.File(poisoned, "r+") as fh:
        rng = np.random.default_rng(0)
        for f in np.setdiff1d(np.arange(len(scene.frame_names)), held_out):
            fh["frames/images"][f] = rng.integers(0, 256, fh["frames/images"].shape[1:], dtype=np.uint8)
    again = run_reconstruction_quality_stage(
        toy_files["recon"], poisoned, toy_files["split"], toy_files["root"] / "poisoned_quality.h5", {"max_frames": 0}
    )
    all_held_out = run_reconstruction_quality_stage(
        toy_files["recon"],
        toy_files["scene"],
        toy_files["split"],
        toy_files["root"] / "all_quality.h5",
        {"max_frames": 0},
    )
    assert read_reconstruction_quality(again) == read_reconstruction_quality(all_held_out)
    assert read_reconstruction_quality(again)["num_frames"] == T_OBS
    # each frame's own camera, row for row: a scene whose held-out frames each have their own camera id
    relabelled = toy_files["root"] / "relabelled_scene.h5"
    shutil.copyfile(toy_files["scene"], relabelled)
    with h5py.File(relabelled, "r+") as fh:
        cameras = fh["frames/camera_id"][()]
        cameras[held_out] = 100 + np.arange(held_out.size)[::-1]
        fh["frames/camera_id"][...] = cameras
    per_camera = run_reconstruction_quality_stage(
        toy_files["recon"],
        relabelled,
        toy_files["split"],
        toy_files["root"] / "relabelled_quality.h5",
        {"max_frames": 0},
    )
    rows = read_per_frame(per_camera)
    assert list(rows["camera_ids"]) == [int(cameras[f]) for f in read_artefact(per_camera)["frame_ids"]]
    assert list(rows["timesteps"]) == [int(scene.time_index[f]) for f in read_artefact(per_camera)["frame_ids"]]
    # a split without held-out views at observed times: nothing to measure
    none_h5 = write_split(
        toy_files["root"] / "no_heldout_split.h5",
        dataclasses.replace(split, frame_ids={**split.frame_ids, "evaluation_observed": np.zeros(0, np.int64)}),
    )
    empty = run_reconstruction_quality_stage(
        toy_files["recon"], toy_files["scene"], none_h5, toy_files["root"] / "empty_quality.h5"
    )
    assert read_reconstruction_quality(empty) == {} and read_artefact(empty)["frame_ids"].shape == (0,)
    assert read_per_frame(empty)["camera_ids"].shape == (0,)
    with h5py.File(out, "r+") as fh:  # one camera id per rendered frame
        cameras = fh["camera_ids"][()]
        del fh["camera_ids"]
        fh.create_dataset("camera_ids", data=cameras[:2], fletcher32=True)
    with pytest.raises(MogafError, match=r"recon\.h5: entry 'camera_ids' has shape \(2,\), expected \(3,\)"):
        read_per_frame(out)
    with h5py.File(out, "r+") as fh:  # an artefact written before camera ids were recorded still reads
        del fh["camera_ids"]
    assert read_per_frame(out)["camera_ids"] is None
    with h5py.File(out, "r+") as fh:  # the observed motion's figures must be numbers
        kept = fh.attrs["observed_motion"]
        fh.attrs["observed_motion"] = 'json:{"epe_3d": "small"}'
    with pytest.raises(MogafError, match=r"recon\.h5: attribute 'observed_motion' is not a mapping of errors"):
        read_reconstruction_quality(out)
    with h5py.File(out, "r+") as fh:
        fh.attrs["observed_motion"] = kept
        del fh["timesteps"]
        fh.create_dataset("timesteps", data=np.zeros(2, np.int64), fletcher32=True)
    with pytest.raises(
        MogafError, match=r"recon\.h5: entry 'timesteps' has shape \(2,\), but 3 frame\(s\) were rendered"
    ):
        read_reconstruction_quality(out)


def test_observed_motion_carries_ground_truth_points_with_the_model():
    """GT points attached at the last observed step and carried back by the
    model's trajectories: no error for a model that moves as the points do (a
    spin and a fall); a model whose last step is off by d has that velocity
    error at the last step; a ground truth of other steps is refused."""
    from types import SimpleNamespace

    from scipy.spatial.transform import Rotation

    from mogaf.reconstruction_quality.measure import observed_motion

    rng = np.random.default_rng(0)
    T = 7
    steps = np.arange(T, dtype=np.float64)
    turns = Rotation.from_rotvec(np.outer(0.15 * steps, [0.2, 0.3, 1.0]))
    shift = np.stack([0.02 * steps, -0.005 * steps**2, 0 * steps], axis=1)

    def moved(points):  # (P, 3) -> (P, T, 3) under the rigid motion
        return np.stack([turns[k].apply(points) + shift[k] for k in range(T)], axis=1)

    centres = rng.uniform(-0.5, 0.5, (60, 3))
    xyzw = turns.as_quat()
    wxyz = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    model = SimpleNamespace(trajectory_means=moved(centres), trajectory_quats=np.tile(wxyz, (60, 1, 1)))
    truth = moved(rng.uniform(-0.5, 0.5, (30, 3)))
    exact = observed_motion(model, truth, 4)
    assert exact["epe_3d"] < 1e-12 and exact["velocity_error"] < 1e-12 and exact["last_velocity_error"] < 1e-12
    assert exact["speed"] == pytest.approx(np.linalg.norm(np.diff(truth, axis=1), axis=-1).mean())
    d = np.array([0.003, -0.004, 0.0])  # the last step 5 mm off
    lagging = SimpleNamespace(
        trajectory_means=model.trajectory_means + np.r_[np.zeros((T - 1, 3)), d[None]][None],
        trajectory_quats=model.trajectory_quats,
    )
    off = observed_motion(lagging, truth, 4)
    assert off["last_velocity_error"] == pytest.approx(0.005, rel=1e-9)
    assert off["epe_3d"] == pytest.approx(0.005 * (T - 1) / T, rel=1e-9)
    with pytest.raises(MogafError, match=r"recon\.h5: the model has 7 observed steps.*\(30, 6, 3\)"):
        observed_motion(model, truth[:, 1:], 4, "recon.h5")
    unknown = truth.copy()
    unknown[:10, 2] = np.nan  # points without a position at some step are left out
    assert observed_motion(model, unknown, 4) == pytest.approx(observed_motion(model, truth[10:], 4))
    assert "still_jitter" not in exact  # every point moves
    # a still body beside it: its points carried by still Gaussians that jitter by +-1 mm along x
    body = rng.uniform(-0.5, 0.5, (40, 3)) + [3.0, 0.0, 0.0]
    wobble = np.zeros((40, T, 3))
    wobble[:, :, 0] = 0.001 * (-1.0) ** np.arange(T)
    both = SimpleNamespace(
        trajectory_means=np.concatenate([model.trajectory_means, body[:, None] + wobble]),
        trajectory_quats=np.concatenate([model.trajectory_quats, np.tile([1.0, 0, 0, 0], (40, T, 1))]),
    )
    still = observed_motion(both, np.concatenate([truth, np.repeat(body[:5, None], T, axis=1)]), 1)
    assert still["still_points"] == 5
    jitter = np.abs(0.001 * (-1.0) ** np.arange(T) - 0.001 * np.mean((-1.0) ** np.arange(T))).mean()
    assert still["still_jitter"] == pytest.approx(jitter, rel=1e-9)


def test_rigid_init_stage(toy_files):
    groups_h5 = toy_files["root"] / "groups_for_rigid.h5"
    run_group_stage(toy_files["recon"], toy_files["priors"], toy_files["scene"], groups_h5, {})
    assert has_rigid_groups(groups_h5)
    out = run_rigid_init_stage(toy_files["recon"], groups_h5, toy_files["root"] / "rigid.h5", {})
    r = read_rigid_init(out)
    assert list(r["group_ids"]) == [0, 1]
    assert r["rotations"].shape == (2, T_OBS, 3, 3) and r["residual_rms"].shape == (2, T_OBS)
    assert np.allclose(np.linalg.det(r["rotations"]), 1.0, atol=1e-9)
    # each group's fitted motion, and the residual it reports
    model = toy_files["model"]
    g = load_groups(groups_h5)
    for i, k in enumerate(r["group_ids"]):
        m = g.members(int(k))
        pred = np.einsum("tij,pj->pti", r["rotations"][i], model.fg.means[m]) + r["translations"][i][None]
        rms = np.sqrt(((pred - model.trajectory_means[m]) ** 2).sum(-1).mean(0))
        assert np.allclose(rms, r["residual_rms"][i], atol=1e-6)
        # the toy objects move rigidly: the fit leaves none of their motion (R = I, t = 0 would leave it all)
        unmoved = np.sqrt(((model.fg.means[m][:, None] - model.trajectory_means[m]) ** 2).sum(-1).mean(0))
        assert unmoved.max() > 0.1 and rms.max() < 1e-9, (rms.max(), unmoved.max())


def toy_groups(labels: np.ndarray, instance_id: list[int]) -> Groups:
    """The toy scene's true grouping (one group per object) with the given mask identities."""
    return Groups(
        group_id=labels - 1,
        rigid=np.ones(2, np.int8),
        static=np.zeros(2, np.int8),
        instance_id=np.array(instance_id),
        names=["sphere", "box"],
        rigid_source=["label"] * 2,
        method="ours",
        params=dict(DEFAULT_PARAMS),
    )


def test_quality_metric_parts(toy_files):
    gt = np.array([[0, 1, 1], [2, 2, 0]])
    pred = np.array([[0, 1, 0], [2, 2, 2]])
    inter, union = per_object_iou(gt, pred, np.array([1, 2]))
    assert list(inter) == [1, 2] and list(union) == [2, 3]
    assert adjusted_rand_index(gt, gt + 5) == pytest.approx(1.0)
    # Perfect groups (= GT instances) render close to the GT masks.
    perfect = toy_groups(toy_files["labels"], instance_id=[1, 2])
    frames = load_scene(toy_files["scene"], read_split(toy_files["split"]).frame_ids["evaluation_observed"][::4])
    q = grouping_quality(toy_files["model"], perfect, frames, pixels="all", backend="torch")
    assert q["num_frames"] == 3 and q["ari"] > 0.85 and min(q["per_object_iou"]) > 0.7
    q_fg = grouping_quality(toy_files["model"], perfect, frames, backend="torch")
    assert q_fg["pixels"] == "foreground" and q_fg["num_pixels"] < q["num_pixels"]
    # Swapping the two groups' identities destroys the IoU, not the ARI.
    swapped = Groups(**{**perfect.__dict__, "instance_id": np.array([2, 1])})
    q2 = grouping_quality(toy_files["model"], swapped, frames, backend="torch")
    assert max(q2["per_object_iou"]) < 0.2 and q2["ari"] == pytest.approx(q_fg["ari"])


def test_assigned_iou_matches_per_pixel_reference():
    """The overlap-matrix IoU equals counting pixels of the relabelled image."""
    rng = np.random.default_rng(0)
    gt = rng.integers(0, 4, size=(5, 9, 11))  # 3 GT labels + background
    pred = rng.integers(0, 6, size=gt.shape)  # 5 groups + background
    overlap = np.bincount((pred * 4 + gt).ravel(), minlength=6 * 4).reshape(6, 4)
    assigned = largest_overlap(overlap)
    assert assigned[0] == 0 and assigned.shape == (6,)
    for mapping in (assigned, np.array([0, 1, 1, 3, 0, 2])):
        inter, union = assigned_iou(overlap, mapping)
        ref_inter, ref_union = per_object_iou(gt, mapping[pred], np.array([1, 2, 3]))
        np.testing.assert_array_equal(inter, ref_inter)
        np.testing.assert_array_equal(union, ref_union)


def _segments_of(frames, parts_of_box: bool) -> Segments:
    """GT segments from the toy masks: sphere one piece; the box one piece or
    two (left and right of its pixels' median column in each frame)."""
    label = np.asarray(frames.instance_mask, np.uint16).copy()
    if not parts_of_box:
        return Segments(label=label, instance=np.array([1, 2]), names=["sphere", "box"])
    for f in range(len(label)):
        rows, cols = np.nonzero(label[f] == 2)
        right = cols > np.median(cols)
        label[f][rows[right], cols[right]] = 3
    return Segments(label=label, instance=np.array([1, 2, 2]), names=["sphere", "box/left", "box/right"])


def test_quality_from_segments(toy_files):
    perfect = toy_groups(toy_files["labels"], instance_id=[1, 2])
    frames = load_scene(toy_files["scene"], read_split(toy_files["split"]).frame_ids["evaluation_observed"][::4])
    from_masks = grouping_quality(toy_files["model"], perfect, frames, backend="torch")
    # segments equal to the masks score exactly as the masks do
    with_segments = dataclasses.replace(frames, segments=_segments_of(frames, parts_of_box=False))
    q = grouping_quality(toy_files["model"], perfect, with_segments, backend="torch")
    assert q["object_matching"] == "mask identity" and "per_part_iou" not in q
    for key in ("per_object_iou", "object_ids", "object_names", "ari", "num_pixels"):
        assert q[key] == from_masks[key]
    # a scene that ships no masks: groups carry no identity and are matched
    # to the object they overlap most, so the perfect grouping scores the same
    no_masks = dataclasses.replace(with_segments, instance_mask=None, instances=None)
    anonymous = Groups(**{**perfect.__dict__, "instance_id": np.array([-1, -1])})
    q_anon = grouping_quality(toy_files["model"], anonymous, no_masks, backend="torch")
    assert q_anon["object_matching"] == "largest overlap"
    assert q_anon["per_object_iou"] == from_masks["per_object_iou"] and q_anon["ari"] == from_masks["ari"]
    # so does a grouping that read one foreground mask: its identity names no object
    foreground = dataclasses.replace(
        with_segments,
        instance_mask=(frames.instance_mask > 0).astype(np.int32),
        instances=Instances(ids=[1], names=["foreground"], rigid=[-1]),
    )
    one_identity = Groups(**{**perfect.__dict__, "instance_id": np.array([1, 1])})
    q_fg = grouping_quality(toy_files["model"], one_identity, foreground, backend="torch")
    assert q_fg["object_matching"] == "largest overlap" and q_fg["per_object_iou"] == from_masks["per_object_iou"]
    # one group over a two-part box: it is given the part it overlaps most, the other part scores 0
    parts = dataclasses.replace(no_masks, segments=_segments_of(frames, parts_of_box=True))
    q_parts = grouping_quality(toy_files["model"], anonymous, parts, backend="torch")
    assert q_parts["object_names"] == ["sphere", "box"]
    assert q_parts["per_object_iou"] == from_masks["per_object_iou"]
    assert q_parts["part_names"] == ["box/left", "box/right"]
    assert sorted(v == 0.0 for v in q_parts["per_part_iou"]) == [False, True]
    assert 0.2 < max(q_parts["per_part_iou"]) < 0.8


def test_quality_stage_reads_segments_of_a_scene_without_masks(toy_files, tmp_path):
    """scene.h5 with ground-truth segments and no instance masks (a synthetic
    scene that ships none): the stage scores objects and parts from them."""
    full = load_scene(toy_files["scene"])
    segments = _segments_of(full, parts_of_box=True)
    bare = dataclasses.replace(full, instance_mask=None, instances=None, segments=segments)
    scene_h5 = save_scene(tmp_path / "scene.h5", bare, config_digest="test")
    groups = toy_groups(toy_files["labels"], instance_id=[-1, -1])
    groups_h5 = write_groups(tmp_path / "groups.h5", groups)
    out = run_grouping_quality_stage(
        toy_files["recon"], groups_h5, scene_h5, toy_files["split"], tmp_path / "gq.h5", {"max_frames": 4}
    )
    q = read_grouping_quality(out)
    assert q["object_matching"] == "largest overlap" and q["object_names"] == ["sphere", "box"]
    assert min(q["per_object_iou"]) > 0.6 and q["part_names"] == ["box/left", "box/right"]
    # the segments are evaluation data: loading the frames a stage fits on leaves them out
    assert load_scene(scene_h5).segments is None
    rows = read_split(toy_files["split"]).frame_ids["evaluation_observed"][:2]
    np.testing.assert_array_equal(load_segments(scene_h5, rows).label, segments.label[rows])
    with h5py.File(scene_h5, "r+") as fh:
        del fh["segments/names"]
    with pytest.raises(MogafError, match=r"scene\.h5: has no entry 'segments/names'"):
        load_segments(scene_h5, rows)


def test_a_segment_label_past_the_named_segments_is_one_line(toy_files, tmp_path):
    """The same check on both paths: a scene about to be written, and a
    scene.h5 whose labels were changed afterwards."""
    full = load_scene(toy_files["scene"])
    segments = _segments_of(full, parts_of_box=False)  # labels 0, 1, 2
    one_named = dataclasses.replace(segments, instance=np.array([1]), names=["sphere"])
    with pytest.raises(MogafError, match=r"scene\.h5: segment labels go up to 2, but 1 segments are named$"):
        save_scene(tmp_path / "bad" / "scene.h5", dataclasses.replace(full, segments=one_named), config_digest="test")
    assert not (tmp_path / "bad" / "scene.h5").exists()
    scene_h5 = save_scene(tmp_path / "scene.h5", dataclasses.replace(full, segments=segments), config_digest="test")
    with h5py.File(scene_h5, "r+") as fh:
        fh["segments/label"][0, 0, 0] = 5
    with pytest.raises(
        MogafError, match=r"scene\.h5: segment labels go up to 5, but 2 segments are named \(rerun ingest\)"
    ):
        load_segments(scene_h5, np.array([0]))
    np.testing.assert_array_equal(load_segments(scene_h5, np.array([1])).label, segments.label[[1]])


def _printed_after_grouping_the_toy_scene(imports: str, rigid_flags: tuple[int, int], then: str) -> str:
    """What a fresh process prints after `imports`, grouping the two-object
    toy scene (instance rigidity `rigid_flags`, -1: estimated) and `then`."""
    import subprocess
    import sys

    from support.paths import REPO

    code = (
        "import sys; sys.path.insert(0, 'tests')\n"
        f"{imports}\n"
        "from mogaf.grouping.api import group_gaussians\n"
        "from support.toy_grouping import two_object_scene\n"
        f"sc = two_object_scene(seed=0, rigid_flags={rigid_flags!r})\n"
        "groups = group_gaussians(sc.model, sc.masks, sc.frames, sc.instances, {'method': 'ours'})\n"
        "assert groups.num_groups == 2\n"
        f"{then}"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    return res.stdout.strip()


def test_the_group_and_rigid_init_stages_do_not_import_torch():
    """Grouping a scene (its rigidity estimated) and fitting its rigid groups
    is NumPy work (the rigid fits: mogaf.rigid_fit): their jobs do not pay
    torch's import (about a second each; Snakemake sets no torch thread count
    for them: registry `torch_threads`)."""
    from mogaf import registry

    assert not registry.spec("group").torch_threads and not registry.spec("rigid_init").torch_threads
    printed = _printed_after_grouping_the_toy_scene(
        "import numpy as np\nimport mogaf.stages\nfrom mogaf.grouping.stage import rigid_init",
        (-1, -1),
        "assert set(groups.rigid_source) == {'estimated'} and groups.rigid.all()\n"
        "fit = rigid_init(sc.model, groups, {})\n"
        "assert fit['group_ids'].size == 2 and np.isfinite(fit['rotations']).all()\n"
        "print('torch' in sys.modules)",
    )
    assert printed == "False"


def test_the_grouping_stages_do_not_import_scikit_learn():
    """scikit-learn (with the SciPy and pandas parts it pulls, one to two
    seconds per process) is not needed by grouping: the motion features' PCA
    is mogaf's own (grouping.ours.principal_components), rigid_init and
    refine import this package for other names, and grouping_quality computes
    its adjusted Rand index itself."""
    printed = _printed_after_grouping_the_toy_scene(
        "import mogaf.grouping.stage, mogaf.refine.stage, mogaf.grouping.quality",
        (1, 1),
        "print(sorted(m for m in ('sklearn', 'pandas') if m in sys.modules))",
    )
    assert printed == "[]"
