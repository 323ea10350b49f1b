"""Unit checks of the reconstruction stage: Procrustes init, densification, losses, parameters."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mogaf.errors import MogafError


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    Kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * Kx + (1 - math.cos(angle)) * Kx @ Kx


def test_procrustes_init_recovers_rigid_motion_of_lifted_tracks():
    """Tracks of a rigidly moving point set, lifted from depth maps, give back the motion as a basis."""
    from mogaf.recon.data import TrainData
    from mogaf.recon.init_tracks import bases_from_clusters, lift_tracks
    from mogaf.recon.interpolation import fill_in_time
    from mogaf.representation import rot6d_to_matrix

    rng = np.random.default_rng(0)
    H = W = 200
    F = 5
    K = np.array([[180.0, 0, W / 2], [0, 180.0, H / 2], [0, 0, 1]])
    w2c = np.eye(4)
    w2c[:3, 3] = [0, 0, 4.0]
    # points on a 7x7 grid in the image at the canonical frame, random depths
    g = (np.arange(7) * 24 + 30).astype(float)
    uv0 = np.stack(np.meshgrid(g + 0.5, g + 0.5), -1).reshape(-1, 2)
    z0 = rng.uniform(3.5, 4.5, size=len(uv0))
    rays = np.concatenate([uv0, np.ones((len(uv0), 1))], 1) @ np.linalg.inv(K).T
    X0 = rays * z0[:, None] - w2c[:3, 3]
    motions = [(_rot(np.array([0.2, 1.0, 0.1]), 0.08 * f), np.array([0.05 * f, -0.03 * f, 0.02 * f])) for f in range(F)]
    xy = np.zeros((len(X0), F, 2), np.float32)
    depth = np.zeros((F, H, W), np.float32)
    for f, (R, t) in enumerate(motions):
        Xf = X0 @ R.T + t
        cam = Xf + w2c[:3, 3]
        uv = (cam @ K.T)[:, :2] / cam[:, 2:]
        xy[:, f] = uv
        px = np.floor(uv).astype(int)
        assert len({tuple(p) for p in px}) == len(px)  # one point per pixel
        depth[f, px[:, 1], px[:, 0]] = cam[:, 2]
    data = TrainData(
        images=np.zeros((F, H, W, 3), np.float32),
        fg_masks=np.ones((F, H, W), np.float32),
        K=np.repeat(K[None], F, 0),
        w2c=np.repeat(w2c[None], F, 0),
        tidx=np.arange(F),
        timesteps=np.arange(F),
        frame_ids=np.arange(F),
        layout="iphone",
        background=np.ones(3, np.float32),
        depth=depth,
        depth_valid=depth > 0,
        tracks_xy=xy,
        tracks_visible=np.ones((len(X0), F), bool),
        tracks_query=np.zeros(len(X0), np.int64),
    )
    xyz, ok = lift_tracks(data)
    assert ok.all()
    xyz = fill_in_time(xyz, ok, data.tidx.astype(float))
    for f, (R, t) in enumerate(motions):
        np.testing.assert_allclose(xyz[:, f], X0 @ R.T + t, atol=1e-4)
    cano = 2
    rot, tr, info = bases_from_clusters(xyz, ok, np.zeros(len(X0), np.int64), np.array([0]), cano, data.tidx, F)
    Rc, tc = motions[cano]
    for f, (R, t) in enumerate(motions):
        # basis maps canonical positions (frame `cano`) to frame f: X_f = R_rel X_c + t_rel
        R_rel = R @ Rc.T
        t_rel = t - R_rel @ tc
        Rb = rot6d_to_matrix(torch.tensor(rot[0, f])).numpy()
        np.testing.assert_allclose(Rb, R_rel, atol=1e-4)
        np.testing.assert_allclose(tr[0, f], t_rel, atol=1e-4)
    assert info["procrustes_err_after"] < 1e-4 < info["procrustes_err_before"]


def _model(n_fg: int, n_bg: int, scales_fg: np.ndarray, scales_bg: np.ndarray):
    from mogaf.recon.model import ReconModel

    def part(n, s, motion):
        d = {
            "means": torch.arange(n * 3, dtype=torch.float32).reshape(n, 3) * 0.01,
            "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
            "log_scales": torch.log(torch.tensor(s, dtype=torch.float32))[:, None].repeat(1, 3),
            "opacity_logits": torch.zeros(n),
            "color_logits": torch.zeros(n, 3),
        }
        if motion:
            d["motion_coef_logits"] = torch.zeros(n, 2)
            d["labels"] = torch.arange(n)
        return d

    m = ReconModel(
        part(n_fg, scales_fg, True), torch.zeros(2, 3, 6), torch.zeros(2, 3, 3), part(n_bg, scales_bg, False)
    )
    opts = {k: torch.optim.Adam([p], lr=1e-3) for k, p in m.named_tensors().items()}
    # give every tensor some Adam state
    loss = sum((p * p).sum() for p in m.named_tensors().values())
    loss.backward()
    for o in opts.values():
        o.step()
    return m, opts


def test_densify_clone_split_and_prune_counts():
    from mogaf.recon.densify import SPLIT_SCALE, DensifyRules, DensityStats, control_step

    # fg: 6 Gaussians, bg: 4; extent 1 -> densify scale threshold 0.01
    scales_fg = np.array([0.001, 0.001, 0.05, 0.05, 0.001, 0.05])
    scales_bg = np.array([0.001, 0.05, 0.001, 0.001])
    m, opts = _model(6, 4, scales_fg, scales_bg)
    with torch.no_grad():
        m.fg.get("opacity_logits")[4] = -5.0  # opacity 0.007 -> pruned
        m.bg.get("opacity_logits")[3] = -5.0
    stats = DensityStats(10)
    # crafted statistic: high gradient on fg 0 (small -> clone), fg 2 (big -> split), bg 0 (clone), bg 1 (split)
    stats.grad_acc[:] = 1e-6
    stats.count[:] = 2
    for i in (0, 2, 6, 7):
        stats.grad_acc[i] = 2 * 5e-3
    rules = DensifyRules(grad_threshold=2e-3, scale_threshold=0.01, screen_threshold=10.0, cull_opacity=0.1, extent=1.0)
    gen = torch.Generator().manual_seed(0)
    old_fg_means = m.fg.get("means").detach().clone()
    counts = control_step(m, opts, stats, rules, gen)
    assert counts == {"split": 2, "clone": 2, "culled": 2}
    # fg: 6 - 1 split + 1 clone + 2 halves - 1 pruned = 7; bg: 4 - 1 + 1 + 2 - 1 = 5
    assert (m.num_fg, m.num_bg) == (7, 5)
    assert len(stats) == 12 and stats.count.sum() == 0
    fg_scales = m.fg.scales()[:, 0].detach().numpy()
    assert np.isclose(fg_scales, 0.05 / SPLIT_SCALE, rtol=1e-2).sum() == 2  # the two halves of fg 2
    assert np.isclose(fg_scales, 0.05, rtol=1e-2).sum() == 2  # fg 3 and 5 untouched
    # optimiser state follows the rows; new rows start with zero moments
    for name, p in m.named_tensors().items():
        st = opts[name].state[p]
        assert st["exp_avg"].shape == p.shape, name
    ea = opts["fg.means"].state[m.fg.get("means")]["exp_avg"]
    assert torch.count_nonzero(ea.abs().sum(-1)) == 4  # kept rows (0, 1, 3, 5) have state, the 3 new ones none
    assert m.fg.aux["labels"].tolist()[:4] == [0, 1, 3, 5] and sorted(m.fg.aux["labels"].tolist()[4:]) == [0, 2, 2]
    assert torch.equal(m.fg.get("means")[0], old_fg_means[0])


def test_densify_respects_the_budget():
    from mogaf.recon.densify import DensifyRules, DensityStats, control_step

    m, opts = _model(6, 4, np.full(6, 0.001), np.full(4, 0.001))
    stats = DensityStats(10)
    stats.count[:] = 1
    stats.grad_acc[:] = torch.linspace(1e-2, 2e-2, 10, dtype=torch.float64)  # all want a clone
    rules = DensifyRules(grad_threshold=1e-3, max_gaussians=13, cull_opacity=0.0)
    counts = control_step(m, opts, stats, rules, torch.Generator().manual_seed(0))
    assert counts["clone"] == 3 and m.num_gaussians == 13
    # the highest-gradient candidates (the last three rows: bg 1, 2, 3) were cloned
    assert (m.num_fg, m.num_bg) == (6, 7)


def test_stats_accumulate_in_ndc_units():
    from mogaf.recon.densify import DensityStats

    st = DensityStats(3)
    grad = torch.tensor([[1e-3, 0.0], [0.0, 2e-3], [5.0, 5.0]])
    radii = torch.tensor([2.0, 3.0, 0.0])
    st.accumulate(grad, radii, width=100, height=50, batch_size=2)
    np.testing.assert_allclose(st.grad_acc[:2].numpy(), [1e-3 * 50 * 2, 2e-3 * 25 * 2])
    assert st.count.tolist() == [1, 1, 0] and st.grad_acc[2] == 0
    np.testing.assert_allclose(st.max_radii.numpy(), [0.02, 0.03, 0.0])


def test_losses():
    from mogaf.recon.losses import accel_loss, masked_l1, ssim

    x = torch.rand(1, 20, 24, 3, generator=torch.Generator().manual_seed(0))
    assert abs(float(ssim(x, x)) - 1.0) < 1e-5
    assert float(ssim(x, 1 - x)) < 0.5
    pred = torch.zeros(100, 1)
    gt = torch.zeros(100, 1)
    gt[0] = 100.0  # one outlier is ignored by the 0.98 quantile
    gt[1:] = 1.0
    assert abs(float(masked_l1(pred, gt, None, 0.98)) - 1.0) < 1e-6
    line = torch.linspace(0, 1, 10)[None, :, None].repeat(2, 1, 3)
    assert float(accel_loss(line)) < 1e-6
    # the mean norm of second differences: one of norm 5 (a 3-4-5 step), two of norm 1
    kink = torch.tensor([[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 3.0, 4.0]]])
    assert float(accel_loss(kink)) == pytest.approx(5.0)
    parabola = torch.tensor([[[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0], [6.0, 0, 0]]])
    assert float(accel_loss(parabola)) == pytest.approx(1.0)


def test_jerk_loss_against_numpy_third_differences():
    from mogaf.recon.losses import accel_loss, jerk_loss

    x = torch.randn(4, 11, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    reference = np.linalg.norm(np.diff(x.numpy(), n=3, axis=1), axis=-1).mean()
    assert float(jerk_loss(x)) == pytest.approx(reference, rel=1e-12)
    # constant acceleration costs nothing; a cubic's jerk is the same at every step (6 a)
    t = torch.arange(9, dtype=torch.float64)[None, :, None]
    falling = torch.cat([t, -4.9 * t**2, 0 * t], dim=-1)
    assert float(jerk_loss(falling)) == pytest.approx(0.0, abs=1e-9) and float(accel_loss(falling)) > 9
    assert float(jerk_loss(0.5 * t**3)) == pytest.approx(3.0)
    # too short for a third difference: zero, with a gradient
    short = torch.ones(2, 3, 3, requires_grad=True)
    jerk_loss(short).backward()
    assert float(jerk_loss(short)) == 0.0 and short.grad is not None


def test_jerk_prior_keeps_the_speed_of_an_accelerating_trajectory_at_both_ends():
    """Fit a trajectory to noisy samples of a falling point under each smoothness
    prior (recon.smooth_bases): the acceleration prior shrinks the acceleration,
    so the fitted velocity is off at both ends of the observation; the jerk
    prior leaves constant acceleration alone."""
    from mogaf.recon.losses import basis_smoothness

    T = 30
    t = torch.arange(T, dtype=torch.float64)
    truth = torch.stack([0.02 * t, -0.004 * t**2, 0 * t], dim=-1)[None]  # (1, T, 3)
    noisy = truth + 5e-4 * torch.randn(truth.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    rot = torch.zeros(1, T, 6, dtype=torch.float64)
    end_error = {}
    for prior in ("acceleration", "jerk"):
        x = noisy.clone().requires_grad_(True)
        opt = torch.optim.Adam([x], lr=2e-3)
        for _ in range(500):
            opt.zero_grad()
            loss = ((x - noisy) ** 2).sum(-1).mean() + 1e-2 * basis_smoothness(rot, x, 1.0, prior)
            loss.backward()
            opt.step()
        fit = x.detach()[0]
        end_error[prior] = [
            float(torch.linalg.norm((fit[i + 1] - fit[i]) - (truth[0, i + 1] - truth[0, i]))) for i in (0, T - 2)
        ]
    # first and last step's velocity error (the true speed there: 0.02 and 0.23 per step)
    assert all(j < 0.2 * a for j, a in zip(end_error["jerk"], end_error["acceleration"], strict=True)), end_error


def test_blend_bases_gives_each_basis_alone_and_orthonormalises_a_blend():
    """Against matrices built elsewhere (scipy), not against the model's own conversions."""
    from scipy.spatial.transform import Rotation

    from mogaf.representation import blend_bases

    rots = Rotation.from_rotvec([[0.3, -0.2, 0.5], [-1.0, 0.4, 0.2], [0.0, 0.0, 0.0]]).as_matrix()
    # two time steps per basis: the rotation, then its transpose
    frames = np.stack([rots, rots.transpose(0, 2, 1)], axis=1)  # (B, T, 3, 3)
    rot6d = torch.tensor(frames[..., :2, :].reshape(3, 2, 6))  # rows b1, b2
    transl = torch.tensor(np.arange(18, dtype=np.float64).reshape(3, 2, 3))
    R, t = blend_bases(torch.eye(3, dtype=torch.float64), rot6d, transl)
    assert R.shape == (3, 2, 3, 3) and t.shape == (3, 2, 3)
    np.testing.assert_allclose(R.numpy(), frames, atol=1e-12)
    np.testing.assert_array_equal(t.numpy(), transl.numpy())
    R, t = blend_bases(torch.tensor([[0.5, 0.5, 0.0]], dtype=torch.float64), rot6d, transl)
    a1, a2 = frames[:2, :, 0].mean(0), frames[:2, :, 1].mean(0)  # the blended rows, per time step
    b1 = a1 / np.linalg.norm(a1, axis=-1, keepdims=True)
    b2 = a2 - (b1 * a2).sum(-1, keepdims=True) * b1
    b2 /= np.linalg.norm(b2, axis=-1, keepdims=True)
    np.testing.assert_allclose(R[0].numpy(), np.stack([b1, b2, np.cross(b1, b2)], axis=-2), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R[0].numpy()), 1.0, atol=1e-12)
    np.testing.assert_allclose(t[0].numpy(), transl[:2].numpy().mean(0), atol=1e-12)


def test_params_are_checked():
    from mogaf.recon.params import DEFAULT_PARAMS, resolve_params

    assert resolve_params({})["iterations"] == DEFAULT_PARAMS["iterations"]
    assert resolve_params({"iterations": 1000, "iterations_scale": 0.25})["iterations"] == 250
    with pytest.raises(MogafError, match="recon: unknown parameter"):
        resolve_params({"iteration": 3})
    with pytest.raises(MogafError, match="integer"):
        resolve_params({"num_bases": 2.5})
    with pytest.raises(MogafError, match="one of"):
        resolve_params({"device": "tpu"})


@pytest.mark.parametrize("q", [0.5, 0.95, 0.98, 0.999])
def test_linear_quantile_equals_torch_quantile_bit_for_bit(q):
    from mogaf.recon.losses import linear_quantile

    gen = torch.Generator().manual_seed(11)
    for trial in range(60):
        n = int(torch.randint(1, 30000, (1,), generator=gen))
        x = torch.rand(n, generator=gen) ** 3
        if trial % 3 == 0:
            x = (x * 10).round() / 10  # many ties
        if trial % 5 == 0:
            x = x.double()
        assert torch.equal(linear_quantile(x, q), torch.quantile(x, q)), (n, q, x.dtype)
    with_nan = torch.tensor([0.1, float("nan"), 0.3])
    assert torch.isnan(linear_quantile(with_nan, q)) and torch.isnan(torch.quantile(with_nan, q))


def test_last_dim_variance_equals_torch_var_bit_for_bit_forward_and_backward():
    """The log-scale variance regulariser's kernel against torch.var (the
    reference): the same float32 bits for the value and the gradient, at
    scales and offsets where cancellation matters, for widths 2-4; float64 and
    wider inputs go to torch.var itself."""
    from mogaf.recon.losses import last_dim_variance

    gen = torch.Generator().manual_seed(5)
    for scale in (1e-3, 1.0, 1e3):
        for offset in (0.0, -5.0, 100.0):
            for width in (2, 3, 4):
                x = torch.randn(20000, width, generator=gen) * scale + offset
                weight = torch.randn(20000, generator=gen)
                grads = []
                for fn in (lambda t: torch.var(t, dim=-1), last_dim_variance):
                    leaf = x.clone().requires_grad_(True)
                    value = fn(leaf)
                    (value * weight).sum().backward()
                    grads.append((value.detach(), leaf.grad))
                (ref, ref_grad), (ours, our_grad) = grads
                assert torch.equal(ours, ref) and torch.equal(our_grad, ref_grad), (scale, offset, width)
    wide = torch.randn(5, 16, generator=gen, dtype=torch.float64)
    assert torch.equal(last_dim_variance(wide), torch.var(wide, dim=-1))


def test_a_softmax_read_several_times_per_step_is_computed_once_with_the_same_bits():
    from mogaf.optim import Adam
    from mogaf.recon.model import last_dim_softmax

    gen = torch.Generator().manual_seed(0)
    logits = torch.nn.Parameter(torch.randn(500, 10, generator=gen) * 3)
    heads = [torch.randn(500, 10, generator=gen) for _ in range(3)]

    def loss_and_grad(read):
        logits.grad = None
        loss = sum(((read() * h) ** 2).sum() * (k + 1) for k, h in enumerate(heads))
        loss.backward()
        return loss.detach(), logits.grad.clone()

    cache: list = []
    want = loss_and_grad(lambda: torch.softmax(logits, dim=-1))
    got = loss_and_grad(lambda: last_dim_softmax(logits, cache))
    assert torch.equal(want[0], got[0]) and torch.equal(want[1], got[1])  # three reads, one softmax
    first = cache[2]
    assert last_dim_softmax(logits, cache) is not first and cache[2] is first
    # an optimiser step (in place) or a new tensor computes it again
    Adam([logits], lr=0.5).step()
    assert torch.equal(last_dim_softmax(logits, cache), torch.softmax(logits, dim=-1)) and cache[2] is not first
    other = torch.nn.Parameter(logits.detach().clone() * 2)
    assert torch.equal(last_dim_softmax(other, cache), torch.softmax(other, dim=-1)) and cache[0] is other


def test_isometry_neighbours_and_distances_against_brute_force():
    """nearest_neighbours: each point's k nearest others (of distinct points,
    never itself), as a dense sort finds them; pair_distances: their Euclidean distances, and a
    finite gradient where two points coincide (a densification clone)."""
    from mogaf.recon.losses import nearest_neighbours, pair_distances

    gen = torch.Generator().manual_seed(0)
    pts = torch.rand(200, 3, generator=gen, dtype=torch.float64)
    nbrs = nearest_neighbours(pts, 5)
    dense = torch.cdist(pts, pts)
    dense.fill_diagonal_(float("inf"))
    expected = dense.argsort(dim=1)[:, :5]
    assert torch.equal(nbrs, expected)
    d = pair_distances(pts, nbrs, 0.0)
    assert torch.allclose(d, torch.gather(dense, 1, expected), rtol=0, atol=1e-12)
    assert nearest_neighbours(pts[:3], 8).shape == (3, 2)  # k capped at N - 1
    assert nearest_neighbours(pts[:1], 8).shape == (1, 0)
    twins = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], requires_grad=True)
    pair_distances(twins, nearest_neighbours(twins, 1), 1e-6).sum().backward()
    assert torch.isfinite(twins.grad).all()
    # Exact duplicates (clones): a point is never its own neighbour, whichever twin the tree returns first.
    clones = torch.cat([pts[:50], pts[:50], pts[:50], pts[50:]])
    nbrs = nearest_neighbours(clones, 4)
    assert not (nbrs == torch.arange(len(clones))[:, None]).any()
    assert (clones[nbrs[:50, :2]] == clones[:50, None]).all()  # its two clones first, at distance 0


def test_isometry_prior_is_blind_to_rigid_motion_and_sees_stretching():
    """The recon trainer's w_isometry term: zero for any rigid motion between
    the two steps (however fast), positive and growing with a stretch."""
    from types import SimpleNamespace

    from mogaf.recon.trainer import Trainer

    gen = torch.Generator().manual_seed(1)
    a = torch.rand(300, 3, generator=gen)
    fake = SimpleNamespace(
        model=SimpleNamespace(num_fg=300, fg=SimpleNamespace(get=lambda name: a)),
        p=SimpleNamespace(isometry_neighbours=8),
        dev=torch.device("cpu"),
        scale=1.0,
        _nbrs=None,
    )
    fake._isometry_neighbours = lambda: Trainer._isometry_neighbours(fake)
    c, s = math.cos(0.7), math.sin(0.7)
    rot = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    moved = a @ rot.T + torch.tensor([5.0, -3.0, 2.0])
    assert float(Trainer._stretch(fake, a, moved)) < 1e-5
    small = float(Trainer._stretch(fake, a, a * 1.01))
    large = float(Trainer._stretch(fake, a, a * 1.05))
    assert 0 < small < large
