"""mogaf.render: forward against the dense reference, gradients, extreme cases, backends."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from mogaf.errors import MogafError
from mogaf.render import cpu, rasterize, resolve_backend
from mogaf.render.projection import project_gaussians
from support.paths import REPO

F64 = torch.float64
FAST = ["cpu", "torch"]


def _rotation(g: torch.Generator, scale: float) -> torch.Tensor:
    w = (torch.rand(3, generator=g, dtype=F64) - 0.5) * 2 * scale
    S = torch.tensor([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]], dtype=F64)
    return torch.linalg.matrix_exp(S)


def random_scene(seed, n, width, height, channels=3, dtype=F64, margin=0.15, px_sigma=(0.5, 5.0)):
    """Random Gaussians in front of a random camera: (means, quats, scales, opacities, features, viewmat, K)."""
    g = torch.Generator().manual_seed(seed)
    fx = fy = float(max(width, height))
    K = torch.tensor([[fx, 0, width / 2 + 0.3], [0, fy, height / 2 - 0.2], [0, 0, 1]], dtype=F64)
    z = 1.5 + 3 * torch.rand(n, generator=g, dtype=F64)
    u = (torch.rand(n, generator=g, dtype=F64) * (1 + 2 * margin) - margin) * width
    v = (torch.rand(n, generator=g, dtype=F64) * (1 + 2 * margin) - margin) * height
    cam = torch.stack([(u - K[0, 2]) * z / fx, (v - K[1, 2]) * z / fy, z], -1)
    R = _rotation(g, 0.3)
    t = torch.randn(3, generator=g, dtype=F64) * 0.3
    viewmat = torch.eye(4, dtype=F64)
    viewmat[:3, :3] = R
    viewmat[:3, 3] = t
    means = (cam - t) @ R  # world = R^T (cam - t)
    lo, hi = px_sigma
    sig = lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=F64)
    scales = sig * z[:, None] / fx
    quats = torch.randn(n, 4, generator=g, dtype=F64)
    opac = 0.05 + 0.9 * torch.rand(n, generator=g, dtype=F64)
    feats = torch.rand(n, channels, generator=g, dtype=F64)
    return tuple(x.to(dtype) for x in (means, quats, scales, opac, feats, viewmat, K))


def _outputs(out):
    return out.features, out.alpha, out.depth


def _grads(backend, scene, width, height, background=None, weights_seed=0):
    params = [p.clone().requires_grad_() for p in scene[:5]]
    out = rasterize(*params, scene[5], scene[6], width, height, background=background, backend=backend)
    g = torch.Generator().manual_seed(weights_seed)
    loss = sum((o * torch.randn(o.shape, generator=g, dtype=o.dtype)).sum() for o in _outputs(out))
    grads = torch.autograd.grad(loss, params, allow_unused=True)
    return out, [torch.zeros_like(p) if gr is None else gr for p, gr in zip(params, grads)]


# ---------------------------------------------------------------------------
# Forward and gradients against the dense reference (float64).


@pytest.mark.parametrize("backend", FAST)
@pytest.mark.parametrize(
    "seed,n,width,height,channels",
    [(0, 40, 33, 27, 3), (1, 120, 48, 40, 1), (2, 300, 64, 45, 5), (3, 60, 70, 21, 9), (4, 500, 40, 40, 4)],
)
def test_forward_and_grads_match_dense_reference(backend, seed, n, width, height, channels):
    scene = random_scene(seed, n, width, height, channels)
    bg = torch.linspace(0.1, 0.9, channels, dtype=F64)
    ref, gref = _grads("reference", scene, width, height, background=bg)
    out, gout = _grads(backend, scene, width, height, background=bg)
    assert out.backend == backend
    for a, b in zip(_outputs(out), _outputs(ref)):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-5)
    torch.testing.assert_close(out.radii, ref.radii)
    torch.testing.assert_close(out.visible, ref.visible)
    torch.testing.assert_close(out.means2d, ref.means2d, rtol=0, atol=1e-9)
    torch.testing.assert_close(out.depths, ref.depths)
    for a, b in zip(gout, gref):
        scale = max(1.0, b.abs().max().item())
        torch.testing.assert_close(a, b, rtol=0, atol=1e-7 * scale)
    assert ref.alpha.max() > 0.5  # the scenes overlap


def test_early_stop_matches_reference():
    # Many opaque Gaussians: most pixels stop at T <= 1e-4.
    scene = list(random_scene(7, 400, 24, 20, 3, px_sigma=(2.0, 6.0)))
    scene[3] = torch.full_like(scene[3], 0.9)
    ref, gref = _grads("reference", scene, 24, 20)
    assert (1 - ref.alpha).min() < 1e-3
    for backend in FAST:
        out, gout = _grads(backend, scene, 24, 20)
        for a, b in zip(_outputs(out), _outputs(ref)):
            torch.testing.assert_close(a, b, rtol=0, atol=1e-5)
        for a, b in zip(gout, gref):
            torch.testing.assert_close(a, b, rtol=0, atol=1e-7 * max(1.0, b.abs().max().item()))


def test_cpu_independent_of_tile_size():
    """(Thread counts: test_kernel_threads_change_no_bit, on a scene large enough to split.)"""
    scene = random_scene(11, 200, 53, 37, 3)
    base = rasterize(*scene, 53, 37, backend="cpu", tile_size=16)
    for tile in (5, 8, 13, 32, 64):
        out = rasterize(*scene, 53, 37, backend="cpu", tile_size=tile)
        for a, b in zip(_outputs(out), _outputs(base)):
            torch.testing.assert_close(a, b, rtol=0, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_kernel_threads_change_no_bit(monkeypatch, dtype):
    """The kernels may use idle cores (mogaf.cores): every output and
    gradient is the same bits with 1, 2 and 3 threads, on a scene that every
    kernel splits between threads (a thread per 8,192 Gaussians projected or
    in view to bin, per 4,096 tile intersections to composite)."""
    from mogaf.cores import ENV, kernel_threads
    from mogaf.devices import torch_threads

    scene = random_scene(12, 30000, 96, 72, 3, dtype=dtype, px_sigma=(0.5, 2.0))
    runs = []
    for n in ("1", "2", "3"):
        monkeypatch.setenv(ENV, n)
        with torch_threads(1):  # torch's own count is the floor: one, so that n decides
            assert kernel_threads() == int(n)
            out, grads = _grads("cpu", scene, 96, 72, background=torch.tensor([0.2, 0.3, 0.4], dtype=dtype))
        runs.append((_outputs(out), grads))
    for outs, grads in runs[1:]:
        for a, b in zip(outs + tuple(grads), runs[0][0] + tuple(runs[0][1])):
            assert torch.equal(a, b)


def test_kernel_threads_follow_the_idle_cores_or_the_setting(monkeypatch):
    from mogaf import cores

    # over one second on 2 cores: others used 0.1 s (the core is free) or 0.9 s (taken)
    assert cores.usable_cores(busy_s=1.1, own_cpu_s=1.0, wall_s=1.0, ncpus=2) == 2
    assert cores.usable_cores(busy_s=1.9, own_cpu_s=1.0, wall_s=1.0, ncpus=2) == 1
    # this process's own second thread is not another process's load
    assert cores.usable_cores(busy_s=2.0, own_cpu_s=2.0, wall_s=1.0, ncpus=2) == 2
    assert cores.usable_cores(busy_s=5.0, own_cpu_s=0.5, wall_s=1.0, ncpus=4) == 1
    assert cores.usable_cores(busy_s=1.5, own_cpu_s=1.0, wall_s=1.0, ncpus=4) == 3
    assert cores.usable_cores(busy_s=0.0, own_cpu_s=0.0, wall_s=0.0, ncpus=2) == 1
    torch_threads = max(1, torch.get_num_threads())
    monkeypatch.setattr(cores, "idle_cores", lambda: pytest.fail("the setting decides without sampling"))
    monkeypatch.setenv(cores.ENV, "3")
    assert cores.cores() == 3 and cores.kernel_threads() == max(3, torch_threads)
    with cores.shared_by(3):  # three threads of this process call the kernels at once
        assert cores.kernel_threads() == torch_threads
    assert cores.kernel_threads() == max(3, torch_threads)
    for bad in ("two", "0", "-1"):
        monkeypatch.setenv(cores.ENV, bad)
        with pytest.raises(MogafError, match="MOGAF_CORES must be a whole number >= 1"):
            cores.cores()
    monkeypatch.delenv(cores.ENV)
    monkeypatch.setattr(cores, "idle_cores", lambda: 4)
    assert cores.cores() == 4 and cores.kernel_threads() == max(4, torch_threads)


def test_a_cgroup_cpu_quota_bounds_the_cores():
    from mogaf.cores import quota_cores

    assert quota_cores(cpu_max="max 100000\n") is None
    assert quota_cores(cpu_max="100000 100000\n") == 1
    assert quota_cores(cpu_max="150000 100000") == 2  # a container's --cpus=1.5
    assert quota_cores(cpu_max="20000 100000") == 1
    assert quota_cores(cfs_quota_us="-1\n", cfs_period_us="100000\n") is None
    assert quota_cores(cfs_quota_us="400000", cfs_period_us="100000") == 4
    assert quota_cores(cpu_max="garbled") is None and quota_cores() is None


def test_idle_cores_sample_this_process_cpu_set():
    from mogaf.cores import FIRST_INTERVAL_S, _busy_seconds, _IdleCores

    sampler = _IdleCores()
    if sampler.limit < 2 or _busy_seconds(sampler.cpus) is None:
        pytest.skip("one CPU, or no /proc/stat or CPU affinity here: the kernels use torch's thread count")
    assert sampler() == 1 and sampler.usable is None  # one sample is no measurement yet
    time.sleep(FIRST_INTERVAL_S * 1.5)  # a caller's first measurement comes sooner than the next ones
    assert 1 <= sampler() <= len(sampler.cpus) and sampler.usable is not None
    assert _busy_seconds(sampler.cpus) >= 0.0


@pytest.mark.parametrize("backend", FAST)
def test_float32_close_to_float64_reference(backend):
    scene = random_scene(5, 300, 64, 48, 3)
    ref = rasterize(*scene, 64, 48, backend="reference")
    out = rasterize(*(x.float() for x in scene), 64, 48, backend=backend)
    assert out.features.dtype == torch.float32
    for a, b in zip(_outputs(out), _outputs(ref)):
        torch.testing.assert_close(a.double(), b, rtol=0, atol=2e-3)


# ---------------------------------------------------------------------------
# gradcheck (float64, tiny scenes).


def _tiny_scene():
    scene = list(random_scene(3, 5, 12, 10, 2, margin=0.05, px_sigma=(0.8, 2.5)))
    scene[3] = torch.tensor([0.3, 0.6, 0.85, 0.5, 0.7], dtype=F64)
    return scene


@pytest.mark.parametrize("backend", ["cpu", "torch", "reference"])
def test_gradcheck_tiny_scene(backend):
    means, quats, scales, opac, feats, viewmat, K = _tiny_scene()
    bg = torch.tensor([0.2, 0.7], dtype=F64)

    def fn(m, q, s, o, f):
        return _outputs(rasterize(m, q, s, o, f, viewmat, K, 12, 10, background=bg, backend=backend))

    inputs = [x.clone().requires_grad_() for x in (means, quats, scales, opac, feats)]
    assert rasterize(*inputs, viewmat, K, 12, 10, backend=backend).visible.all()
    # The dense reference is slow to differentiate 600 times: random-projection mode.
    fast = backend == "reference"
    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=fast)


@pytest.mark.parametrize("backend", ["cpu", "torch"])
def test_gradcheck_viewmat(backend):
    means, quats, scales, opac, feats, viewmat, K = _tiny_scene()

    def fn(vm):
        return _outputs(rasterize(means, quats, scales, opac, feats, vm, K, 12, 10, backend=backend))

    vm = [viewmat.clone().requires_grad_()]
    assert torch.autograd.gradcheck(fn, vm, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=backend == "torch")


def test_cpu_projection_matches_torch_projection():
    scene = random_scene(9, 200, 40, 30, 3, margin=0.5)
    means, quats, scales, opac, _, viewmat, K = scene
    quats = quats.clone()
    quats[0] = 0
    ins = [x.clone().requires_grad_() for x in (means, quats, scales, viewmat)]
    pt = project_gaussians(ins[0], ins[1], ins[2], opac, ins[3], K, 40, 30)
    pc = cpu.project_cpu(ins[0], ins[1], ins[2], opac, ins[3], K, 40, 30)
    torch.testing.assert_close(pc[3], pt.radii)
    torch.testing.assert_close(pc[4], pt.visible)
    ws = [torch.randn_like(t) for t in pc[:3]]
    lt = sum((a * w).sum() for a, w in zip((pt.means2d, pt.conics, pt.depths), ws))
    lc = sum((a * w).sum() for a, w in zip(pc[:3], ws))
    for a, b in zip(pc[:3], (pt.means2d, pt.conics, pt.depths)):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    for a, b in zip(torch.autograd.grad(lc, ins), torch.autograd.grad(lt, ins)):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)


# ---------------------------------------------------------------------------
# Extreme cases: finite values and gradients, and agreement with the reference.


def _extreme(case: str):
    W, H = 16, 12
    means, quats, scales, opac, feats, viewmat, K = [x.clone() for x in random_scene(21, 12, W, H, 3)]
    fx = K[0, 0].item()
    ident = torch.tensor([1.0, 0, 0, 0], dtype=F64)
    cam = torch.eye(4, dtype=F64)
    if case == "behind":
        means[:6, 2] = torch.tensor([-1.0, -0.5, -1e-3, 0.0, 1e-3, 0.009])
        viewmat = cam
    elif case == "near_plane":
        viewmat = cam
        means[:4] = torch.tensor([[0.0, 0.0, 0.011], [0.01, 0.0, 0.02], [0.0, 0.0, 0.01], [-0.02, 0.01, 0.05]])
        scales[:4] = torch.tensor([[0.05, 0.05, 0.5], [0.2, 0.02, 0.1], [0.01, 0.01, 0.01], [0.3, 0.3, 0.3]])
    elif case == "border":
        viewmat = cam
        z = 2.0
        px = torch.tensor([0.0, W, -3.0, W + 2.5, W + 60.0, -60.0, 0.5, W - 0.5])
        py = torch.tensor([0.0, H, H / 2, 0.0, H / 2, H / 2, -2.0, H + 3.0])
        means[:8] = torch.stack([(px - K[0, 2]) * z / fx, (py - K[1, 2]) * z / fx, torch.full((8,), z)], -1)
    elif case == "needle":
        scales = scales * torch.tensor([1.0, 1e-4, 1e-4], dtype=F64) * 3
        scales[:3] = torch.tensor([[1e-2, 1e-6, 1e-6], [1e-6, 1e-2, 1e-6], [1.0, 1e-4, 1e-4]])
    elif case == "huge":
        scales[:3] = torch.tensor([[100.0, 100.0, 100.0], [30.0, 50.0, 1e-3], [1e3, 1e-2, 1e3]])
    elif case == "stacked":
        n = 10000
        viewmat = cam
        means = torch.tensor([[0.01, -0.02, 2.0]], dtype=F64).repeat(n, 1)
        means[: n // 2, 2] += torch.linspace(0, 1e-3, n // 2, dtype=F64)
        quats = ident.repeat(n, 1)
        scales = torch.full((n, 3), 0.01, dtype=F64)
        opac = torch.linspace(0.1, 0.9, n, dtype=F64)
        feats = torch.rand(n, 3, generator=torch.Generator().manual_seed(0), dtype=F64)
        W, H = 9, 7
        K = torch.tensor([[10.0, 0, 4.5], [0, 10.0, 3.5], [0, 0, 1]], dtype=F64)
    elif case == "zero_quat":
        quats[:4] = 0
        quats[4] = torch.tensor([1e-300, 0, 0, 0])
    else:
        raise AssertionError(case)
    return [means, quats, scales, opac, feats, viewmat, K], W, H


EXTREMES = ["behind", "near_plane", "border", "needle", "huge", "stacked", "zero_quat"]


@pytest.mark.parametrize("case", EXTREMES)
def test_extreme_cases_finite_and_match_reference(case):
    scene, W, H = _extreme(case)
    ref, gref = _grads("reference", scene, W, H)
    for o in (*_outputs(ref), *gref):
        assert torch.isfinite(o).all()
    for backend in FAST:
        out, gout = _grads(backend, scene, W, H)
        for o in (*_outputs(out), *gout, out.means2d):
            assert torch.isfinite(o).all(), (backend, case)
        for a, b in zip(_outputs(out), _outputs(ref)):
            torch.testing.assert_close(a, b, rtol=0, atol=1e-5)
        for a, b in zip(gout, gref):
            torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7 * max(1.0, b.abs().max().item()))
    if case == "behind":
        assert not ref.visible[:5].any()
    if case == "stacked":
        assert (1 - ref.alpha).min() > 1e-4  # the early stop kept T above 1e-4
    if case == "zero_quat":
        assert torch.equal(gref[1][:5], torch.zeros_like(gref[1][:5]))


@pytest.mark.parametrize("case", EXTREMES)
def test_extreme_cases_finite_float32(case):
    scene, W, H = _extreme(case)
    scene = [x.float() for x in scene]
    for backend in FAST:
        out, grads = _grads(backend, scene, W, H)
        for o in (*_outputs(out), *grads):
            assert torch.isfinite(o).all(), (backend, case)


# ---------------------------------------------------------------------------
# API: outputs, means2d gradient, background, errors, backend choice.


@pytest.mark.parametrize("backend", ["cpu", "torch", "reference"])
def test_means2d_gradient_for_densification(backend):
    scene = random_scene(2, 30, 20, 16, 3)
    params = [p.clone().requires_grad_() for p in scene[:5]]
    out = rasterize(*params, scene[5], scene[6], 20, 16, backend=backend)
    assert out.means2d.shape == (30, 2) and out.radii.shape == (30, 2) and out.radii.dtype == torch.int32
    assert out.depths.shape == (30,) and out.visible.dtype == torch.bool
    assert out.retain_means2d_grad()
    out.features.sum().backward()
    g = out.means2d_grad
    assert g is not None and g.shape == (30, 2) and torch.isfinite(g).all()
    assert g[out.visible].abs().sum() > 0
    assert torch.equal(g[~out.visible], torch.zeros_like(g[~out.visible]))
    # Same value through the tensor itself (CPU backends) and as d loss / d (u, v).
    params2 = [p.detach().clone().requires_grad_() for p in scene[:5]]
    out2 = rasterize(*params2, scene[5], scene[6], 20, 16, backend=backend)
    out2.means2d.retain_grad()
    out2.features.sum().backward()
    torch.testing.assert_close(out2.means2d.grad, g)
    params3 = [p.detach().clone().requires_grad_() for p in scene[:5]]
    out3 = rasterize(*params3, scene[5], scene[6], 20, 16, backend="reference")
    out3.retain_means2d_grad()
    out3.features.sum().backward()
    torch.testing.assert_close(g, out3.means2d_grad, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("backend", ["cpu", "torch"])
def test_gradcheck_compositor(backend):
    # The 2D compositors alone: gradients for means2d, conics, opacities, features,
    # depths (composited as the alpha-normalised depth channel) and the background.
    from mogaf.render.cpu import composite_cpu
    from mogaf.render.torch_raster import composite_torch

    means, quats, scales, opac, feats, viewmat, K = _tiny_scene()
    p = project_gaussians(means, quats, scales, opac, viewmat, K, 12, 10)
    inputs = [x.detach().clone().requires_grad_() for x in (p.means2d, p.conics, opac, feats, p.depths)]
    bg = torch.tensor([0.3, -0.2], dtype=F64, requires_grad=True)

    def f(m, c, o, ft, z, b):
        if backend == "cpu":
            return composite_cpu(m, c, o, ft, z, p.radii, 12, 10, background=b)
        acc, alpha = composite_torch(m, c, o, torch.cat([ft, z[:, None]], 1), p.radii, z, 12, 10)
        return acc[..., :-1] + (1 - alpha) * b, alpha, acc[..., -1:] / alpha.clamp(min=1e-10)

    inputs.append(bg)

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_background_and_depth_semantics():
    scene = random_scene(6, 50, 30, 20, 2)
    plain = rasterize(*scene, 30, 20, backend="cpu")
    bg = torch.tensor([0.25, -1.0], dtype=F64)
    out = rasterize(*scene, 30, 20, background=bg, backend="cpu")
    torch.testing.assert_close(out.features, plain.features + (1 - plain.alpha) * bg)
    torch.testing.assert_close(out.depth, plain.depth)
    seen = plain.alpha[..., 0] > 0.5
    z = plain.depths[plain.visible]
    d = plain.depth[..., 0][seen]
    assert (d >= z.min() - 1e-9).all() and (d <= z.max() + 1e-9).all()
    scalar = rasterize(*scene, 30, 20, background=3.0, backend="cpu")  # a number: the same in every channel
    torch.testing.assert_close(scalar.features, plain.features + (1 - plain.alpha) * 3.0)


def test_nothing_visible_keeps_graph():
    means, quats, scales, opac, feats, viewmat, K = random_scene(1, 5, 10, 8, 3)
    means = means.clone()
    means[:, 2] = -5.0
    viewmat = torch.eye(4, dtype=F64)
    for backend in ["cpu", "torch", "reference"]:
        p = means.clone().requires_grad_()
        f = feats.clone().requires_grad_()
        out = rasterize(p, quats, scales, opac, f, viewmat, K, 10, 8, background=0.5, backend=backend)
        assert not out.visible.any() and torch.all(out.features == 0.5) and torch.all(out.alpha == 0)
        with torch.no_grad():
            assert not rasterize(p, quats, scales, opac, f, viewmat, K, 10, 8, backend=backend).retain_means2d_grad()
        (out.features.sum() + out.depth.sum()).backward()
        assert torch.equal(p.grad, torch.zeros_like(p)) and torch.equal(f.grad, torch.zeros_like(f))


def test_input_errors():
    scene = random_scene(0, 4, 8, 8, 3)
    with pytest.raises(MogafError, match="quats has shape"):
        rasterize(scene[0], scene[1][:, :3], *scene[2:], 8, 8)
    with pytest.raises(MogafError, match="features has shape"):
        rasterize(*scene[:4], scene[4][:3], *scene[5:], 8, 8)
    with pytest.raises(MogafError, match="unknown backend"):
        rasterize(*scene, 8, 8, backend="vulkan")
    with pytest.raises(MogafError, match="background"):
        rasterize(*scene, 8, 8, background=torch.zeros(2, dtype=F64))
    with pytest.raises(MogafError, match="image size"):
        rasterize(*scene, 0, 8)


def test_backend_resolution(monkeypatch):
    cpu_dev = torch.device("cpu")
    monkeypatch.delenv("MOGAF_RENDER_BACKEND", raising=False)
    assert resolve_backend("auto", cpu_dev) == ("cpu" if cpu.available() else "torch")
    monkeypatch.setenv("MOGAF_RENDER_BACKEND", "torch")
    assert resolve_backend("auto", cpu_dev) == "torch"
    assert resolve_backend("reference", cpu_dev) == "reference"  # explicit names win
    scene = random_scene(0, 4, 8, 8, 3)
    assert rasterize(*scene, 8, 8).backend == "torch"
    with pytest.raises(MogafError, match="needs CUDA"):
        resolve_backend("gsplat", cpu_dev)
    monkeypatch.delenv("MOGAF_RENDER_BACKEND")
    if not torch.cuda.is_available():
        with pytest.raises(MogafError, match="gsplat"):
            resolve_backend("auto", torch.device("cuda"))
    with pytest.raises(MogafError, match="CPU tensors only"):
        resolve_backend("cpu", torch.device("cuda"))


def test_kernel_build_failure_falls_back_with_one_warning(monkeypatch, tmp_path):
    saved = dict(cpu._state)
    monkeypatch.setenv("MOGAF_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("MOGAF_RENDER_BACKEND", raising=False)
    try:
        for cxx in ("/nonexistent/g++", "false"):
            cpu._state.update(lib=None, tried=False, error=None)
            monkeypatch.setenv("CXX", cxx)
            if cxx.startswith("/"):
                monkeypatch.setenv("PATH", str(tmp_path))  # no compiler at all
            else:
                monkeypatch.setenv("PATH", os.environ["PATH"].split(os.pathsep, 1)[0] + os.pathsep + "/bin:/usr/bin")
                monkeypatch.setattr(cpu, "compiler", lambda: "/bin/false")
            scene = random_scene(0, 6, 8, 8, 3)
            with pytest.warns(RuntimeWarning, match="C\\+\\+ CPU kernel is unavailable"):
                out = rasterize(*scene, 8, 8)
            assert out.backend == "torch"
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                assert rasterize(*scene, 8, 8).backend == "torch"  # warned once only
            with pytest.raises(MogafError, match="unavailable"):
                rasterize(*scene, 8, 8, backend="cpu")
    finally:
        cpu._state.clear()
        cpu._state.update(saved)


def test_import_is_cheap():
    code = (
        "import sys, mogaf; assert 'torch' not in sys.modules and 'mogaf.render' not in sys.modules\n"
        "import mogaf.render, mogaf.render.cpu as c\n"
        "assert 'gsplat' not in sys.modules and not c._state['tried']\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


def test_the_kernel_builds_without_torch_where_the_renderer_looks_for_it(tmp_path):
    """`python -m mogaf.kernel_build` (make setup runs it while torch installs)
    imports no torch, names the library cpu.load() opens, and without a
    compiler says so and exits 0 (the torch compositor is the fallback)."""
    from mogaf import kernel_build

    env = {**os.environ, "MOGAF_CACHE_DIR": str(tmp_path)}
    code = (
        "import sys, mogaf.kernel_build as k; assert 'torch' not in sys.modules\n"
        "print(k.library_path(k.compiler() or 'g++'))\n"
    )
    named = subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True, text=True)
    assert Path(named.stdout.strip()).parent == tmp_path / "kernels"
    if cpu.available():  # the library this process opened is where the build puts it
        assert any(kernel_build.library_path(kernel_build.compiler()) == Path(p) for p in _loaded_libraries())
    bare = {**env, "CXX": "", "PATH": str(tmp_path)}  # no compiler to be found
    out = subprocess.run(
        [sys.executable, "-m", "mogaf.kernel_build"], env=bare, capture_output=True, text=True, cwd=REPO
    )
    assert out.returncode == 0 and "no C++ compiler" in out.stdout
    assert not (tmp_path / "kernels").exists() or not any((tmp_path / "kernels").iterdir())


def _loaded_libraries() -> list[str]:
    """Shared objects mapped into this process (Linux)."""
    maps = Path("/proc/self/maps")
    if not maps.exists():
        return []
    return sorted({line.split()[-1] for line in maps.read_text().splitlines() if line.rstrip().endswith(".so")})


MEMORY_RUN = """
import resource, sys
import torch
sys.path[:0] = sys.argv[1:]
from test_render import random_scene
from mogaf.render import rasterize
scene = random_scene(8, 4000, 384, 384, 3, px_sigma=(0.5, 1.5))
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
for backend in ("cpu", "torch"):
    params = [p.clone().requires_grad_() for p in scene[:5]]
    out = rasterize(*params, scene[5], scene[6], 384, 384, backend=backend)
    (out.features.sum() + out.alpha.sum()).backward()
    assert torch.isfinite(params[0].grad).all(), backend
print((resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) // 1024)
"""


def test_memory_scales_with_covered_pixels():
    """4,000 Gaussians on 384 x 384, forward and backward: a dense N x H x W
    float64 tensor would need 4.7 GB; the fast backends' peak grows far less."""
    res = subprocess.run(
        [sys.executable, "-c", MEMORY_RUN, str(Path(__file__).parent)],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "MOGAF_CORES": "1"},
    )
    assert res.returncode == 0, res.stderr[-2000:]
    grown_mib = int(res.stdout.split()[-1])
    assert grown_mib < 1024, grown_mib


def test_gsplat_backend_argument_mapping(monkeypatch):
    # Without a GPU: a stand-in gsplat checks how arguments and outputs are mapped.
    import types

    from mogaf.render import gsplat_backend

    calls = {}
    scene = random_scene(3, 20, 16, 12, 3, dtype=torch.float32)

    def fake_rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **kw):
        calls.update(kw, viewmats=viewmats.shape, Ks=Ks.shape, colors=colors.shape, quats=quats)
        out = rasterize(means, quats, scales, opacities, colors, viewmats[0], Ks[0], width, height, backend="cpu")
        img = torch.cat([out.features, out.depth], -1)[None]
        return img, out.alpha[None], {"means2d": out.means2d[None], "radii": out.radii[None]}

    fake = types.SimpleNamespace(rasterization=fake_rasterization)
    monkeypatch.setitem(sys.modules, "gsplat", fake)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    quats = scene[1].clone()
    quats[0] = 0
    params = [scene[0], quats, *scene[2:5]]
    feats, depth, alpha, node, means2d, radii = gsplat_backend.render_gsplat(
        *params, scene[5], scene[6], 16, 12, 0.01, 1e10, 0.3, 16
    )
    assert calls["render_mode"] == "RGB+ED" and calls["packed"] is False and calls["rasterize_mode"] == "classic"
    assert calls["viewmats"] == (1, 4, 4) and calls["Ks"] == (1, 3, 3) and calls["colors"] == (20, 3)
    assert torch.equal(calls["quats"][0], torch.tensor([1.0, 0, 0, 0]))  # zero quaternion guarded
    ref = rasterize(*params, scene[5], scene[6], 16, 12, backend="cpu")
    for a, b in zip((feats, alpha, depth), _outputs(ref)):
        torch.testing.assert_close(a, b)
    assert node.shape == (1, 20, 2) and means2d.shape == (20, 2) and radii.shape == (20, 2)


# ---------------------------------------------------------------------------
# gsplat parity (GPU only).


@pytest.mark.gpu
def test_gsplat_parity():
    if not torch.cuda.is_available():
        pytest.skip("needs CUDA")
    pytest.importorskip("gsplat")
    scene = random_scene(12, 400, 96, 64, 4, dtype=torch.float32)
    params = [p.clone().requires_grad_() for p in scene[:5]]
    ref = rasterize(*params, scene[5], scene[6], 96, 64, backend="cpu")
    gparams = [p.detach().cuda().requires_grad_() for p in scene[:5]]
    out = rasterize(*gparams, scene[5].cuda(), scene[6].cuda(), 96, 64)
    assert out.backend == "gsplat"
    for a, b in zip(_outputs(out), _outputs(ref)):
        torch.testing.assert_close(a.cpu(), b.detach(), rtol=1e-3, atol=2e-3)
    torch.testing.assert_close(out.radii.cpu(), ref.radii, rtol=0, atol=1)
    torch.testing.assert_close(out.means2d.detach().cpu(), ref.means2d.detach(), rtol=1e-4, atol=1e-3)
    ref.retain_means2d_grad()
    out.retain_means2d_grad()
    sum(o.sum() for o in _outputs(ref)).backward()
    sum(o.sum() for o in _outputs(out)).backward()
    for a, b in zip(gparams, params):
        torch.testing.assert_close(a.grad.cpu(), b.grad, rtol=2e-2, atol=2e-3)
    torch.testing.assert_close(out.means2d_grad.cpu(), ref.means2d_grad, rtol=2e-2, atol=2e-3)


@pytest.mark.parametrize(
    "argv, words",
    [
        (["--sizes", "abc"], "--sizes takes whole numbers >= 1"),
        (["--res", "0"], "--res takes whole numbers >= 1"),
        (["--repeats", "0"], "--repeats must be at least 1, got 0"),
    ],
)
def test_bench_render_checks_its_flags_before_timing(capsys, argv, words):
    from mogaf.bench import render as bench

    with pytest.raises(SystemExit) as exc:
        bench.main(argv)
    assert exc.value.code == 2 and words in capsys.readouterr().err


def test_projection_matches_the_hand_derived_ewa_splat():
    """means2d, conic and radii from the pinhole model and EWA's J Sigma J^T
    (+ eps2d), written out here with numpy: the dense reference shares
    project_gaussians with the fast paths, so this is its own check."""
    fx, fy, cx, cy, W, H, eps2d = 100.0, 80.0, 32.0, 24.0, 64, 48, 0.3
    K = torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=torch.float64)
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, 3] = torch.tensor([0.0, 0.0, 2.0])  # the world origin lies 2 ahead of the camera
    means = torch.tensor([[0.1, -0.2, 1.0], [0.0, 0.0, 0.5]], dtype=torch.float64)
    a = math.radians(30)
    quats = torch.tensor([[1.0, 0, 0, 0], [math.cos(a / 2), 0, 0, math.sin(a / 2)]], dtype=torch.float64)
    scales = torch.tensor([[0.05, 0.05, 0.05], [0.08, 0.02, 0.04]], dtype=torch.float64)
    opac = torch.tensor([1.0, 0.5], dtype=torch.float64)
    p = project_gaussians(means, quats, scales, opac, viewmat, K, W, H, eps2d=eps2d)
    rot_z = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])  # 30 deg about z
    for i, R in enumerate((np.eye(3), rot_z)):
        X, Y, Z = means[i].numpy() + [0.0, 0.0, 2.0]
        np.testing.assert_allclose(p.means2d[i].numpy(), [fx * X / Z + cx, fy * Y / Z + cy], rtol=1e-12)
        J = np.array([[fx / Z, 0, -fx * X / Z**2], [0, fy / Z, -fy * Y / Z**2]])
        cov2d = J @ R @ np.diag(scales[i].numpy() ** 2) @ R.T @ J.T + eps2d * np.eye(2)
        inv = np.linalg.inv(cov2d)
        np.testing.assert_allclose(p.conics[i].numpy(), [inv[0, 0], inv[0, 1], inv[1, 1]], rtol=1e-10, atol=1e-12)
        extent = min(math.sqrt(2 * math.log(float(opac[i]) * 255)), 3.33)  # sigmas where alpha reaches 1/255
        expected = [math.ceil(extent * math.sqrt(cov2d[0, 0])), math.ceil(extent * math.sqrt(cov2d[1, 1]))]
        assert p.radii[i].tolist() == expected
    assert p.depths.tolist() == [3.0, 2.5] and p.visible.all()
