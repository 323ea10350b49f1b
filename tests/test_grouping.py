"""Motion-aware grouping (ours), Gaga-4D, voting, rigidity and static flags."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.metrics import adjusted_rand_score

from mogaf.errors import MogafError
from mogaf.grouping import DEFAULT_PARAMS
from mogaf.grouping.api import group_gaussians
from mogaf.grouping.core import InstanceTable, MaskFrames, mask_gaussians
from mogaf.grouping.rigidity import decide_rigidity, estimate_rigid, still_members, two_class_threshold
from mogaf.grouping.stage import rigid_init
from mogaf.grouping.voting import knn_vote
from mogaf.scene import Instances
from support.toy_grouping import look_at, model_from_points, two_object_scene


@pytest.fixture(scope="module")
def scene_far():
    return two_object_scene(seed=0)


@pytest.fixture(scope="module")
def scene_close():
    return two_object_scene(seed=1, close=True)


def _check_valid(groups, N):
    K = groups.num_groups
    assert groups.group_id.shape == (N,) and groups.group_id.dtype == np.int64
    assert K >= 1 and groups.group_id.min() >= 0 and groups.group_id.max() < K
    assert np.all(np.bincount(groups.group_id, minlength=K) > 0)  # no empty group kept
    for arr in (groups.rigid, groups.static, groups.instance_id):
        assert arr.shape == (K,)
    assert set(np.unique(groups.rigid)) <= {0, 1} and set(np.unique(groups.static)) <= {0, 1}
    assert len(groups.names) == K and len(groups.rigid_source) == K
    assert set(groups.rigid_source) <= {"label", "config", "estimated"}


@pytest.mark.parametrize("which", ["scene_far", "scene_close"])
def test_ours_recovers_two_objects(which, request):
    sc = request.getfixturevalue(which)
    g = group_gaussians(sc.model, sc.masks, sc.frames, sc.instances, {"method": "ours"})
    _check_valid(g, len(sc.labels))
    assert adjusted_rand_score(sc.labels, g.group_id) > 0.9
    assert g.num_groups == 2 and g.names == ["sphere", "box"]
    assert list(g.instance_id) == [1, 2]
    assert list(g.rigid) == [1, 1] and g.rigid_source == ["label", "label"]
    assert list(g.static) == [0, 0]
    # Deterministic (conflict resolution included).
    g2 = group_gaussians(sc.model, sc.masks, sc.frames, sc.instances, {"method": "ours"})
    assert np.array_equal(g.group_id, g2.group_id)


SLAB_K = np.array([[100.0, 0, 48], [0, 100.0, 32], [0, 0, 1]])


def _touching_slabs(seed: int, T: int, step: float, n: int = 700):
    """Two slabs in contact at x = 0, a (label 1) rising and b (label 2)
    sinking by `step` a frame: trajectories (2n, T, 3), labels, and a camera
    (SLAB_K, w2c) looking at the x-z plane from -y."""
    rng = np.random.default_rng(seed)
    a = np.c_[rng.uniform(-1, 0, n), rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n)]
    b = np.c_[rng.uniform(0, 1, n), rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n)]
    traj = np.zeros((2 * n, T, 3))
    for t in range(T):
        traj[:n, t] = a + [0, 0, step * t]
        traj[n:, t] = b + [0, 0, -step * t]
    labels = np.r_[np.ones(n, int), np.full(n, 2)]
    return traj, labels, look_at(np.array([0.0, -5.0, 0.0]), np.zeros(3))


def test_ours_needs_the_motion_feature_on_touching_objects():
    """Objects in contact: space alone leaks, the motion coefficients separate."""
    from support.toy_grouping import splat_instance_masks

    traj, labels, w2c = _touching_slabs(3, T=8, step=0.15)
    model = model_from_points(traj, labels, coef_noise=0.1)
    # Masks only at the first step; exact masks (no dilation), so every seed is right.
    K = SLAB_K
    masks = splat_instance_masks(traj[:, 0], labels, K, w2c, 96, 64, radius=0)[None]
    frames = MaskFrames(K=K[None], w2c=w2c[None], time_index=[0])
    inst = Instances(ids=[1, 2], names=["a", "b"], rigid=[1, 1])
    ours = group_gaussians(model, masks, frames, inst, {"method": "ours"})
    assert adjusted_rand_score(labels, ours.group_id) > 0.99
    flat = group_gaussians(model, masks, frames, inst, {"method": "ours", "pca_components": 0})
    assert adjusted_rand_score(labels, flat.group_id) < 0.95


def test_mask_majority_outvotes_one_keyframes_wrong_seeds():
    """A mask that bled across a contact at the first keyframe seeds part of
    object a as b. Keeping the first group leaves them in b; with
    mask_majority the four later keyframes' masks give them back to a."""
    from support.toy_grouping import splat_instance_masks

    T = 5
    traj, labels, w2c = _touching_slabs(4, T=T, step=0.1)
    model = model_from_points(traj, labels, coef_noise=0.1)
    K = SLAB_K
    masks = np.stack([splat_instance_masks(traj[:, t], labels, K, w2c, 96, 64, radius=0) for t in range(T)])
    band = (labels == 1) & (traj[:, 0, 0] > -0.35)  # a's side of the contact
    bled = splat_instance_masks(traj[band, 0], labels[band], K, w2c, 96, 64, radius=0) > 0
    masks[0][bled] = 2
    frames = MaskFrames(K=np.repeat(K[None], T, 0), w2c=np.repeat(w2c[None], T, 0), time_index=np.arange(T))
    inst = Instances(ids=[1, 2], names=["a", "b"], rigid=[1, 1])
    params = {"method": "ours", "keyframe_stride": 1}
    first = group_gaussians(model, masks, frames, inst, params)
    majority = group_gaussians(model, masks, frames, inst, {**params, "mask_majority": True})
    ids = np.array([1, 2])
    front = (DEFAULT_PARAMS["front_fraction"], DEFAULT_PARAMS["front_patches"])  # the seeds' selection
    idx, which = mask_gaussians(traj[:, 0], masks[0], K, w2c, ids, *front)
    later_a = np.zeros(labels.size, int)  # later keyframes whose mask of a takes the Gaussian
    for t in range(1, T):
        i, w = mask_gaussians(traj[:, t], masks[t], K, w2c, ids, *front)
        later_a[i[w == 0]] += 1
    wrong = idx[(which == 1) & (labels[idx] == 1) & (later_a[idx] >= 2)]  # outvoted 2 (or more) to 1
    assert wrong.size > 20
    assert np.all(first.group_id[wrong] == 1)  # b's group (index 1) kept them
    assert np.all(majority.group_id[wrong] == 0)
    assert majority.attrs["method_diagnostics"]["mask_majority_moved"] >= wrong.size
    assert adjusted_rand_score(labels, majority.group_id) > adjusted_rand_score(labels, first.group_id) + 0.05


def test_mask_majority_identity_needs_over_half_of_the_votes():
    from mogaf.grouping.ours import GROW, SEED, mask_majority_identity

    labels = np.array([0, 0, 1, 1, -1])
    stage = np.array([SEED, GROW, SEED, GROW, -1], dtype=np.int8)
    votes = np.array([[1, 2], [1, 1], [0, 3], [0, 0], [0, 0]])
    assert mask_majority_identity(labels, stage, votes) == 1
    assert list(labels) == [1, 0, 1, 1, -1]  # a tie, no vote: the label stays
    assert list(stage) == [SEED, GROW, SEED, GROW, -1]


@pytest.mark.parametrize("which", ["scene_far", "scene_close"])
def test_gaga4d_gives_a_valid_labelling(which, request):
    sc = request.getfixturevalue(which)
    g = group_gaussians(sc.model, sc.masks, sc.frames, sc.instances, {"method": "gaga4d"})
    _check_valid(g, len(sc.labels))
    assert g.method == "gaga4d" and g.params["overlap_threshold"] == 0.1
    assert set(g.instance_id.tolist()) <= {1, 2}
    assert np.all(g.rigid == 1)
    assert adjusted_rand_score(sc.labels, g.group_id) > 0.5


def test_gaga4d_fragments_when_overlap_is_low(scene_far):
    """A mask whose Gaussians do not overlap the memory bank opens a new group."""
    sc = scene_far
    masks = sc.masks.copy()
    # Frame 0 sees only the left half of the sphere's pixels, the others only the right half.
    cols = np.arange(masks.shape[2])
    sphere_cols = np.flatnonzero((masks == 1).any(axis=(0, 1)))
    mid = int(np.median(sphere_cols))
    masks[0][(masks[0] == 1) & (cols[None, :] >= mid)] = 0
    for f in range(1, len(masks)):
        masks[f][(masks[f] == 1) & (cols[None, :] < mid + 3)] = 0
    g = group_gaussians(sc.model, masks, sc.frames, sc.instances, {"method": "gaga4d", "overlap_threshold": 0.99})
    _check_valid(g, len(sc.labels))
    assert (g.instance_id == 1).sum() >= 2
    assert any(name.startswith("sphere#") for name in g.names)


def test_reseeding_moves_grown_gaussians_but_never_seeded_ones():
    from mogaf.grouping.ours import GROW, SEED, seed

    labels = np.array([0, 0, 1, -1])
    stage = np.array([SEED, GROW, GROW, -1], dtype=np.int8)
    queried = np.array([0.5, 0.5, 0.5, 0.0])
    idx, inst = np.array([0, 1, 2, 3]), np.array([1, 1, 1, 1])
    # default (first kept): only the unassigned one joins
    l1, s1 = labels.copy(), stage.copy()
    assert seed(l1, s1, idx, inst) == 1 and list(l1) == [0, 0, 1, 1]
    # reseed_grown: the grown Gaussian in the other group moves (radius cache reset); the seeded one stays
    l2, s2, q2 = labels.copy(), stage.copy(), queried.copy()
    assert seed(l2, s2, idx, inst, q2) == 2
    assert list(l2) == [0, 1, 1, 1] and list(s2) == [SEED, SEED, GROW, SEED] and list(q2) == [0.5, 0.0, 0.5, 0.0]


@pytest.mark.parametrize(
    ("grow_after_last", "expected"),
    [
        (True, ["seed a", "grow", "seed b", "grow", "vote"]),
        (False, ["seed a", "grow", "seed a", "grow", "seed b", "vote"]),
    ],
)
def test_grouping_steps_in_algorithm_3s_order_or_ours(scene_far, monkeypatch, grow_after_last, expected):
    """Algorithm 3 (grow_after_last_keyframe: false, config/paper.yaml): seed the
    first keyframe, then for every keyframe (the first again) grow and seed,
    then vote; ours grows once more after the last keyframe's seeding."""
    import mogaf.grouping.ours as ours

    sc = scene_far
    a, b = 0, len(sc.frames.time_index) - 1
    assert not np.array_equal(sc.masks[a], sc.masks[b])
    steps: list[str] = []
    for name, label in (("mask_gaussians", None), ("region_grow", "grow"), ("knn_vote", "vote")):
        original = getattr(ours, name)

        def traced(*args, _original=original, _label=label, **kwargs):
            # mask_gaussians(means, mask, ...) seeds: which keyframe's mask it is given
            steps.append(_label or ("seed a" if np.array_equal(args[1], sc.masks[a]) else "seed b"))
            return _original(*args, **kwargs)

        monkeypatch.setattr(ours, name, traced)
    params = {"method": "ours", "grow_after_last_keyframe": grow_after_last}
    labels, _, _ = ours.group_ours(
        sc.model, sc.masks, sc.frames, sc.instances.ids, params, frame_order=np.array([a, b])
    )
    assert steps == expected
    assert np.all(labels >= 0)


@pytest.mark.parametrize("which", ["scene_far", "scene_close"])
def test_reseed_grown_still_recovers_two_objects(which, request):
    sc = request.getfixturevalue(which)
    g = group_gaussians(sc.model, sc.masks, sc.frames, sc.instances, {"method": "ours", "reseed_grown": True})
    assert adjusted_rand_score(sc.labels, g.group_id) > 0.9
    with pytest.raises(MogafError, match="reseed_grown"):
        group_gaussians(sc.model, sc.masks, sc.frames, sc.instances, {"method": "ours", "reseed_grown": 1})


def test_unknown_method_and_params_are_refused(scene_far):
    sc = scene_far
    with pytest.raises(MogafError):
        group_gaussians(sc.model, sc.masks, sc.frames, sc.instances, {"method": "nope"})
    with pytest.raises(MogafError):
        group_gaussians(sc.model, sc.masks, sc.frames, sc.instances, {"typo_param": 1})


def test_static_scene_gives_one_static_group(scene_far):
    sc = scene_far
    T = sc.model.trajectory_means.shape[1]
    still = np.repeat(sc.model.trajectory_means[:, :1], T, axis=1)
    model = model_from_points(still, sc.labels)
    for method in ("ours", "gaga4d"):
        g = group_gaussians(model, sc.masks, sc.frames, sc.instances, {"method": method})
        _check_valid(g, len(sc.labels))
        assert g.num_groups == 1 and g.static[0] == 1 and g.rigid[0] == 1
        assert g.attrs["static_scene"] is True


def test_static_group_is_flagged(scene_far):
    sc = scene_far
    traj = sc.model.trajectory_means.copy()
    box = sc.labels == 2
    traj[box] = traj[box][:, :1]  # the box stands still
    model = model_from_points(traj, sc.labels)
    g = group_gaussians(model, sc.masks, sc.frames, sc.instances, {})
    assert list(g.static) == [0, 1]


def test_single_gaussian_group_and_empty_group(scene_far):
    sc = scene_far
    # A lone Gaussian far from both objects with its own identity (3), and an
    # identity (4) listed but never visible.
    T = sc.model.trajectory_means.shape[1]
    lone = np.zeros((1, T, 3))
    lone[0, :, 2] = 1.6
    lone[0, :, 0] = np.linspace(0.0, 0.2, T)
    traj = np.concatenate([sc.model.trajectory_means, lone])
    labels = np.r_[sc.labels, 3]
    model = model_from_points(traj, labels)
    masks = sc.masks.copy()
    from mogaf.camera import project

    for f in range(len(masks)):
        uv, z = project(lone[:, int(sc.frames.time_index[f])], sc.frames.K[f], sc.frames.w2c[f])
        c, r = np.floor(uv[0]).astype(int)
        assert 0 <= r < masks.shape[1] and 0 <= c < masks.shape[2]
        masks[f, r, c] = 3
    inst = Instances(ids=[1, 2, 3, 4], names=["sphere", "box", "lone", "ghost"], rigid=[1, 1, -1, 0])
    for method in ("ours", "gaga4d"):
        g = group_gaussians(model, masks, sc.frames, inst, {"method": method})
        _check_valid(g, len(labels))
        assert 4 not in g.instance_id  # the empty group is dropped, ids compacted
        k = int(np.flatnonzero(g.instance_id == 3)[0])
        assert g.group_id[-1] == k
        assert g.rigid_source[k] == "estimated" and g.rigid[k] == 1  # < 3 members: rigid
        assert adjusted_rand_score(labels, g.group_id) > (0.9 if method == "ours" else 0.5)
        # The one-Gaussian rigid group goes through rigid_init: a pure translation.
        r = rigid_init(model, g)
        i = int(np.flatnonzero(r["group_ids"] == k)[0])
        assert np.allclose(np.linalg.det(r["rotations"][i]), 1.0) and np.all(np.isfinite(r["translations"][i]))
        assert g.sizes()[k] == 1
        assert np.allclose(r["translations"][i] + lone[0, 0], lone[0], atol=1e-9)
        assert np.allclose(r["rotations"][i], np.eye(3)) and np.allclose(r["residual_rms"][i], 0.0)


def test_rigid_init_tolerates_an_empty_group(scene_far):
    sc = scene_far
    g = group_gaussians(sc.model, sc.masks, sc.frames, sc.instances, {})
    # A third, empty rigid group (as a hand-made groups.h5 could have).
    g.rigid = np.r_[g.rigid, 1].astype(np.int8)
    g.static = np.r_[g.static, 0].astype(np.int8)
    r = rigid_init(sc.model, g)
    assert list(r["group_ids"]) == [0, 1, 2]
    assert np.allclose(r["rotations"][2], np.eye(3)) and np.allclose(r["translations"][2], 0.0)


def test_masks_that_claim_nothing_give_one_unlabelled_group(scene_far):
    sc = scene_far
    g = group_gaussians(sc.model, np.zeros_like(sc.masks), sc.frames, sc.instances, {})
    _check_valid(g, len(sc.labels))
    assert g.num_groups == 1 and g.names == ["unlabelled"] and g.rigid_source == ["estimated"]
    assert g.rigid[0] == 0  # two objects moving differently are not one rigid body


def test_empty_model():
    model = model_from_points(np.zeros((0, 4, 3)))
    frames = MaskFrames(K=np.eye(3)[None], w2c=np.eye(4)[None], time_index=[0])
    g = group_gaussians(model, np.zeros((1, 8, 8), np.int32), frames, None, {})
    assert g.num_groups == 0 and g.group_id.shape == (0,)
    assert rigid_init(model, g)["rotations"].shape == (0, 4, 3, 3)


def test_rigidity_estimate_rigid_vs_nonrigid():
    rng = np.random.default_rng(0)
    P, T = 300, 10
    pts = rng.normal(size=(P, 3)) * [1.0, 0.5, 0.2]
    rigid_traj = np.zeros((P, T, 3))
    wave_traj = np.zeros((P, T, 3))
    for t in range(T):
        a = 0.2 * t
        R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        rigid_traj[:, t] = pts @ R.T + [0.1 * t, 0, 0] + rng.normal(scale=1e-3, size=(P, 3))
        bend = pts.copy()
        bend[:, 2] += 0.4 * np.sin(2.0 * pts[:, 0] + 0.5 * t) * t / T  # a travelling, growing wave
        wave_traj[:, t] = bend @ R.T
    ok, r = estimate_rigid(pts, rigid_traj, DEFAULT_PARAMS["rigidity_threshold"])
    assert ok and r < 0.01
    ok, r = estimate_rigid(pts, wave_traj, DEFAULT_PARAMS["rigidity_threshold"])
    assert not ok and r > 0.05
    # Sources: config override > label > estimate.
    table = InstanceTable(
        ids=np.array([1, 2, 3]),
        names=["a", "b", "c"],
        rigid=np.array([0, -1, -1], np.int8),
        rigid_source=["label", "label", "label"],
    )
    traj = np.concatenate([rigid_traj, wave_traj, rigid_traj])
    canon = np.concatenate([pts, pts, pts])
    gid = np.repeat([0, 1, 2], P)
    params = {**DEFAULT_PARAMS, "rigid_override": {"c": 0}}
    flags, sources, res = decide_rigidity(np.array([0, 1, 2]), table, canon, traj, gid, params)
    assert list(flags) == [0, 0, 0] and sources == ["label", "estimated", "config"]
    assert res[0] == -1 and res[1] > 0.05 and res[2] == -1
    table.rigid[:] = -1
    flags, sources, _ = decide_rigidity(np.array([0, 1]), table, canon, traj, gid, DEFAULT_PARAMS)
    assert list(flags) == [1, 0] and sources == ["estimated", "estimated"]


def test_unlabelled_instances_get_estimated_rigidity(scene_far):
    sc = scene_far
    inst = Instances(ids=[1, 2], names=["sphere", "box"], rigid=[-1, -1])
    g = group_gaussians(sc.model, sc.masks, sc.frames, inst, {})
    assert list(g.rigid) == [1, 1] and g.rigid_source == ["estimated", "estimated"]
    assert np.all(g.diagnostics["group_rigid_residual"] < 0.05)


def test_front_gaussian_selection():
    # 10 Gaussians on the optical axis, one pixel: the closest 40 % are kept.
    pts = np.c_[np.zeros(10), np.zeros(10), np.linspace(5.0, 1.0, 10)]
    K = np.array([[10.0, 0, 4], [0, 10.0, 4], [0, 0, 1]])
    mask = np.zeros((8, 8), np.int32)
    mask[4, 4] = 7
    idx, inst = mask_gaussians(pts, mask, K, np.eye(4), np.array([7]), front_fraction=0.4, num_patches=1)
    assert sorted(idx.tolist()) == [6, 7, 8, 9] and np.all(inst == 0)
    idx, _ = mask_gaussians(pts, mask, K, np.eye(4), np.array([7]), front_fraction=1.0)
    assert idx.size == 10
    # Behind the camera or outside the image: never selected.
    idx, _ = mask_gaussians(-pts, mask, K, np.eye(4), np.array([7]))
    assert idx.size == 0


def test_voting_assigns_everyone_deterministically():
    rng = np.random.default_rng(0)
    feats = rng.normal(size=(500, 3))
    labels = np.full(500, -1)
    labels[feats[:, 0] < -1.0] = 0
    labels[feats[:, 0] > 1.0] = 1
    out, rounds = knn_vote(feats, labels, k=8, fraction=0.5)
    assert np.all(out >= 0) and rounds >= 2
    assert np.all(out[feats[:, 0] < -1.0] == 0) and np.all(out[feats[:, 0] > 1.0] == 1)
    assert np.mean(out[feats[:, 0] < -0.3] == 0) > 0.9 and np.mean(out[feats[:, 0] > 0.3] == 1) > 0.9
    assert np.array_equal(out, knn_vote(feats, labels)[0])
    none, _ = knn_vote(feats, np.full(500, -1))
    assert np.all(none == -1)


def test_rigid_init_recovers_toy_motion(scene_far):
    sc = scene_far
    g = group_gaussians(sc.model, sc.masks, sc.frames, sc.instances, {})
    out = rigid_init(sc.model, g)
    T = sc.model.trajectory_means.shape[1]
    assert list(out["group_ids"]) == [0, 1]
    assert out["rotations"].shape == (2, T, 3, 3) and out["translations"].shape == (2, T, 3)
    assert np.allclose(np.linalg.det(out["rotations"]), 1.0, atol=1e-9)
    assert out["residual_rms"].max() < 1e-6  # GT trajectories are exactly rigid
    # At t = 0 the fit is the identity (canonical = first step).
    assert np.allclose(out["rotations"][:, 0], np.eye(3), atol=1e-6)
    # Only rigid groups are solved.
    g.rigid[:] = [0, 1]
    assert list(rigid_init(sc.model, g)["group_ids"]) == [1]


def test_ari_is_left_out_with_one_ground_truth_object_and_kept_with_two():
    from mogaf.grouping.metrics import ari_section

    gt = np.array([1, 1, 1, 0, 0])  # one object; two background pixels the groups cover
    pred = np.array([1, 1, 2, 1, 2])
    one = ari_section(gt, pred, 1)
    assert "ari" not in one and one["ari_left_out"].startswith("1 object in the ground-truth masks")
    two = ari_section(np.array([1, 1, 2, 2]), np.array([5, 5, 7, 7]), 2)
    assert two == {"ari": 1.0}


def test_adjusted_rand_index_equals_scikit_learns():
    """The pair-counting ARI of the grouping_quality stage (no sklearn import
    there) against scikit-learn's, bit for bit: random labellings, the
    degenerate partitions, and a labelling large enough that the pair products
    overflow int64."""
    from mogaf.grouping.metrics import adjusted_rand_index

    rng = np.random.default_rng(0)
    cases = [
        (np.zeros(5, int), np.zeros(5, int)),
        (np.arange(5), np.arange(5)),
        (np.zeros(5, int), np.arange(5)),
        (np.arange(5), np.zeros(5, int)),
        (np.array([3]), np.array([7])),
    ]
    for _ in range(300):
        n = int(rng.integers(1, 300))
        a = rng.integers(0, int(rng.integers(1, 6)), n)
        b = a.copy() if rng.random() < 0.3 else rng.integers(0, int(rng.integers(1, 6)), n)
        b[rng.random(n) < 0.1] = 9
        cases.append((3 * a - 5, b))
    big = rng.integers(0, 4, 3_000_000)
    cases.append((big, np.where(rng.random(big.size) < 0.9, big, rng.integers(0, 4, big.size))))
    for a, b in cases:
        assert adjusted_rand_index(a, b) == adjusted_rand_score(a, b), (a, b)
    assert adjusted_rand_index(np.array([]), np.array([])) == 1.0


def test_still_members_of_a_moving_group_get_a_static_group(scene_far):
    """One foreground mask over a still box and a moving sphere (a still body
    with one moving part, no instance masks): the split holds the box apart."""
    sc = scene_far
    traj = sc.model.trajectory_means.copy()
    box = sc.labels == 2
    traj[box] = traj[box][:, :1]
    model = model_from_points(traj, sc.labels)
    foreground = (np.asarray(sc.masks) > 0).astype(np.int64)

    def grouping(rigid, mode):
        inst = Instances(ids=[1], names=["foreground"], rigid=[rigid])
        return group_gaussians(model, foreground, sc.frames, inst, {"split_still_members": mode})

    assert grouping(-1, "never").num_groups == 1  # the paper's grouping: one group
    g = grouping(-1, "unlabelled")
    _check_valid(g, len(sc.labels))
    assert g.names == ["foreground", "foreground/still"] and list(g.instance_id) == [1, 1]
    assert list(g.static) == [0, 1] and adjusted_rand_score(sc.labels, g.group_id) > 0.95
    assert g.rigid_source == ["estimated", "estimated"] and g.rigid[0] == 1
    # a mask labelled rigid never splits; one labelled non-rigid only with "not_rigid"
    assert grouping(1, "not_rigid").num_groups == 1
    assert grouping(0, "unlabelled").num_groups == 1 and grouping(0, "not_rigid").num_groups == 2


def test_two_class_threshold_cuts_between_the_modes():
    assert two_class_threshold(np.array([0.0, 0.1, 1.0, 1.1])) == pytest.approx(0.55)
    assert two_class_threshold(np.array([2.0])) == 2.0


def test_still_members_of_a_jittering_body_and_a_swinging_part():
    """70 % of a group jitter (1 cm) in place, 30 % swing (a metre): the
    jitter is cut off from the swing; no cut without two clear classes."""
    rng = np.random.default_rng(0)
    G, T = 400, 20
    pos = np.zeros((G, T, 3))
    pos[:, :, 0] = np.arange(G)[:, None] * 0.01  # a row of members
    moving = np.arange(G) >= 280  # one contiguous part
    pos[moving, :, 2] += np.linspace(0.0, 1.0, T)
    pos += rng.normal(0.0, 0.01, size=pos.shape)
    still = still_members(pos, neighbours=16, ratio=3.0, min_fraction=0.1)
    assert np.array_equal(still, ~moving)
    assert not still_members(pos, neighbours=16, ratio=1e3, min_fraction=0.1).any()  # classes not far enough apart
    assert not still_members(pos, neighbours=16, ratio=3.0, min_fraction=0.35).any()  # the moving part is too small
    pos[:, :, 2] += np.linspace(0.0, 1.0, T)  # everything swings: one class
    assert not still_members(pos, neighbours=16, ratio=3.0, min_fraction=0.1).any()


@pytest.mark.parametrize("shape", [(500, 10), (40, 3), (6, 8)])
def test_principal_components_equal_scikit_learns_pca_to_the_bit(shape):
    from sklearn.decomposition import PCA

    from mogaf.grouping.ours import principal_components

    x = np.random.default_rng(sum(shape)).normal(size=shape) ** 3  # skewed: a few dominant directions
    reference = PCA(n_components=min(shape), svd_solver="full")
    scores, ratios = principal_components(x)
    assert np.array_equal(scores, reference.fit_transform(x))
    assert np.array_equal(ratios, reference.explained_variance_ratio_)
