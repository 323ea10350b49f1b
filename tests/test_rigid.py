"""Weighted Procrustes and rigid-fit residuals (mogaf.rigid, and its NumPy
solver mogaf.rigid_fit against it)."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from mogaf.eager_roma import load as load_roma
from mogaf.rigid import apply_rigid, procrustes_numpy, rigid_fit_residual, weighted_procrustes
from mogaf.rigid_fit import fit_residual, procrustes

roma = load_roma()  # as the pipeline imports it (without torch's compiler)


def _rot(axis, angle) -> torch.Tensor:
    a = torch.as_tensor(axis, dtype=torch.float64)
    return roma.rotvec_to_rotmat(a / a.norm() * angle)


def _check_rotation(R: torch.Tensor, tol: float = 1e-9) -> None:
    R = R.detach().double()
    assert torch.isfinite(R).all()
    eye = torch.eye(3, dtype=torch.float64).expand_as(R)
    assert torch.allclose(R @ R.transpose(-1, -2), eye, atol=tol)
    assert torch.allclose(torch.det(R), torch.ones(R.shape[:-2], dtype=torch.float64), atol=tol)


def test_recovers_known_transform_with_noise():
    g = torch.Generator().manual_seed(1)
    T, P = 6, 200
    R_true = roma.random_rotmat(T, dtype=torch.float64)
    t_true = torch.randn(T, 3, dtype=torch.float64, generator=g)
    src = torch.randn(P, 3, dtype=torch.float64, generator=g)
    noise = 1e-3 * torch.randn(T, P, 3, dtype=torch.float64, generator=g)
    dst = apply_rigid(R_true, t_true, src) + noise
    R, t = weighted_procrustes(src, dst)  # src broadcast over time
    assert R.shape == (T, 3, 3) and t.shape == (T, 3)
    _check_rotation(R)
    angle_err = roma.rotmat_geodesic_distance(R, R_true)
    assert float(angle_err.max()) < 1e-3
    assert float((t - t_true).abs().max()) < 1e-3
    rms = rigid_fit_residual(src, dst, R=R, t=t)
    assert torch.allclose(rms, torch.full((T,), 1e-3 * math.sqrt(3), dtype=torch.float64), rtol=0.2)


def test_exact_recovery_float64_and_float32():
    g = torch.Generator().manual_seed(2)
    R_true = roma.random_rotmat(1, dtype=torch.float64)[0]
    t_true = torch.tensor([0.3, -2.0, 5.0], dtype=torch.float64)
    src = torch.randn(50, 3, dtype=torch.float64, generator=g)
    dst = src @ R_true.T + t_true
    R, t = weighted_procrustes(src, dst)
    assert float((R - R_true).abs().max()) < 1e-9 and float((t - t_true).abs().max()) < 1e-9
    R32, t32 = weighted_procrustes(src.float(), dst.float())
    assert R32.dtype == torch.float32 and t32.dtype == torch.float32
    assert float((R32.double() - R_true).abs().max()) < 1e-5


def test_weights_ignore_outliers():
    g = torch.Generator().manual_seed(3)
    R_true = _rot([1.0, 2.0, 3.0], 0.7)
    src = torch.randn(40, 3, dtype=torch.float64, generator=g)
    dst = src @ R_true.T
    dst[:5] += 10.0  # outliers
    w = torch.ones(40, dtype=torch.float64)
    w[:5] = 0.0
    R, t = weighted_procrustes(src, dst, w)
    assert float((R - R_true).abs().max()) < 1e-9 and float(t.abs().max()) < 1e-9
    assert float(rigid_fit_residual(src, dst, w)) < 1e-9
    # All-zero weights fall back to uniform weights: finite, a rotation.
    R0, t0 = weighted_procrustes(src, dst, torch.zeros(40, dtype=torch.float64))
    _check_rotation(R0)
    assert torch.isfinite(t0).all()


def _degenerate_sets():
    g = torch.Generator().manual_seed(4)
    d = torch.float64
    line = torch.linspace(-1, 1, 7, dtype=d)[:, None] * torch.tensor([1.0, 2.0, -0.5], dtype=d)
    plane = torch.cat([torch.randn(8, 2, dtype=d, generator=g), torch.zeros(8, 1, dtype=d)], 1)
    cloud = torch.randn(10, 3, dtype=d, generator=g)
    reflect = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=d))
    return {
        "one_point": (torch.randn(1, 3, dtype=d, generator=g), torch.randn(1, 3, dtype=d, generator=g)),
        "two_points": (torch.randn(2, 3, dtype=d, generator=g), torch.randn(2, 3, dtype=d, generator=g)),
        "three_points": (torch.randn(3, 3, dtype=d, generator=g), torch.randn(3, 3, dtype=d, generator=g)),
        "all_identical": (torch.ones(6, 3, dtype=d), torch.full((6, 3), 2.0, dtype=d)),
        "collinear": (line, line @ _rot([0.0, 1.0, 1.0], 0.9).T + 1.0),
        "coplanar": (plane, plane @ _rot([1.0, 0.0, 0.3], 2.0).T),
        "reflected": (cloud, cloud @ reflect.T),
        "coplanar_reflected": (plane, plane @ reflect.T),
        "collinear_to_identical": (line, torch.zeros_like(line)),
        "empty": (torch.zeros(0, 3, dtype=d), torch.zeros(0, 3, dtype=d)),
    }


@pytest.mark.parametrize("name", list(_degenerate_sets()))
def test_degenerate_sets_are_finite_with_finite_gradients(name):
    src0, dst0 = _degenerate_sets()[name]
    src = src0.clone().requires_grad_(True)
    dst = dst0.clone().requires_grad_(True)
    w = torch.linspace(0.5, 1.5, src0.shape[0], dtype=torch.float64).requires_grad_(True)
    R, t = weighted_procrustes(src, dst, w)
    _check_rotation(R)
    assert torch.isfinite(t).all()
    g = torch.Generator().manual_seed(5)
    loss = (R * torch.randn(3, 3, dtype=torch.float64, generator=g)).sum() + t.sum()
    loss = loss + rigid_fit_residual(src, dst, w) + rigid_fit_residual(src, dst, w, squared=True)
    loss.backward()
    for x in (src, dst, w):
        assert x.grad is not None and torch.isfinite(x.grad).all(), name
    # Deterministic: the same input gives the same rotation.
    R2, _ = weighted_procrustes(src0, dst0, w.detach())
    assert torch.equal(R.detach(), R2)


def test_no_information_gives_identity():
    R, t = weighted_procrustes(torch.ones(4, 3, dtype=torch.float64), torch.full((4, 3), 3.0, dtype=torch.float64))
    assert torch.allclose(R, torch.eye(3, dtype=torch.float64))
    assert torch.allclose(t, torch.full((3,), 2.0, dtype=torch.float64))


@pytest.mark.parametrize("delta", [0.0, 1e-9, 1e-7, 1e-6])
def test_rotation_near_pi(delta):
    g = torch.Generator().manual_seed(6)
    axis = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    R_true = _rot(axis, math.pi - delta)
    src = torch.randn(30, 3, dtype=torch.float64, generator=g).requires_grad_(True)
    dst = (src.detach() @ R_true.T + torch.tensor([1.0, 0.0, -1.0], dtype=torch.float64)).requires_grad_(True)
    R, t = weighted_procrustes(src, dst)
    _check_rotation(R)
    assert float((R.detach() - R_true).abs().max()) < 1e-8
    (R.sum() + t.sum()).backward()
    assert torch.isfinite(src.grad).all() and torch.isfinite(dst.grad).all()
    # Batched with float32 inputs too.
    R32, _ = weighted_procrustes(src.detach().float()[None].expand(3, -1, -1), dst.detach().float())
    _check_rotation(R32.double(), tol=1e-5)
    assert float((R32.double() - R_true).abs().max()) < 1e-4


def test_gradcheck_well_posed():
    g = torch.Generator().manual_seed(7)
    src = torch.randn(6, 3, dtype=torch.float64, generator=g, requires_grad=True)
    dst = (
        src.detach() @ _rot([1.0, 1.0, 0.0], 0.4).T + 0.05 * torch.randn(6, 3, dtype=torch.float64, generator=g)
    ).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, b: weighted_procrustes(a, b)[0], (src, dst), atol=1e-5)


def test_numpy_wrapper():
    src = np.random.default_rng(8).normal(size=(20, 3))
    R_true = _rot([0.0, 0.0, 1.0], 1.0).numpy()
    R, t = procrustes_numpy(src, src @ R_true.T + 2.0)
    assert np.allclose(R, R_true, atol=1e-9) and np.allclose(t, 2.0, atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(3, 40),
    frames=st.integers(1, 4),
    weighted=st.sampled_from(["none", "per point", "per frame and point"]),
    planar=st.booleans(),
    noise=st.sampled_from([0.0, 1e-3, 0.3]),
    log_scale=st.floats(-4.0, 3.0),
)
def test_numpy_solver_equals_the_torch_one_on_well_posed_fits(seed, n, frames, weighted, planar, noise, log_scale):
    """mogaf.rigid_fit (NumPy, SVD; the group and rigid_init stages) against
    mogaf.rigid (torch, roma): the same R, t and residual to float64 rounding
    wherever the fit has one answer (three or more points not on a line;
    flat sets included), with weights (some negative: clamped at 0; per point
    or per frame and point), a batch of frames and noisy targets."""
    rng = np.random.default_rng(seed)
    src = rng.normal(size=(n, 3)) * 10.0**log_scale
    if planar:
        src[:, 2] = 0.0
    rot = np.stack([_rot(rng.normal(size=3), rng.uniform(0.0, math.pi)).numpy() for _ in range(frames)])
    dst = (
        src @ rot.transpose(0, 2, 1)
        + rng.normal(size=(frames, 1, 3))
        + noise * 10.0**log_scale * rng.normal(size=(frames, n, 3))
    )
    shape = {"none": None, "per point": (n,), "per frame and point": (frames, n)}[weighted]
    w = None if shape is None else rng.uniform(-0.3, 1.0, shape)
    if w is not None:
        w[..., :3] = rng.uniform(0.1, 1.0, shape[:-1] + (3,))  # three points keep a weight: one answer
    tw = None if w is None else torch.from_numpy(w)
    R_t, t_t = weighted_procrustes(torch.from_numpy(src), torch.from_numpy(dst), tw)
    R_n, t_n = procrustes(src, dst, w)
    size = 1.0 + 10.0**log_scale
    assert np.allclose(R_n, R_t.numpy(), rtol=0.0, atol=1e-9)
    assert np.allclose(t_n, t_t.numpy(), rtol=0.0, atol=1e-9 * size)
    assert np.allclose(np.linalg.det(R_n), 1.0, atol=1e-12)
    for squared, unit in ((False, size), (True, size**2)):
        r_t = rigid_fit_residual(torch.from_numpy(src), torch.from_numpy(dst), tw, squared=squared).numpy()
        r_n = fit_residual(src, dst, w, squared=squared)
        assert np.allclose(r_n, r_t, rtol=1e-9, atol=1e-12 * unit)


def test_numpy_solver_edge_cases():
    """An empty set: the identity; weights summing to zero: uniform ones; a
    reflected copy: still a rotation (det +1); float32 points: the float64
    fit; non-finite points: NaN, not an exception; bad shapes: an error."""
    R, t = procrustes(np.zeros((2, 0, 3)), np.zeros((2, 0, 3)))
    assert np.array_equal(R, np.broadcast_to(np.eye(3), (2, 3, 3))) and np.array_equal(t, np.zeros((2, 3)))
    src = np.random.default_rng(1).normal(size=(12, 3))
    dst = src @ _rot([0.0, 1.0, 0.0], 0.7).numpy().T + 3.0
    for a, b in zip(procrustes(src, dst, np.zeros(12)), procrustes(src, dst), strict=True):
        assert np.array_equal(a, b)
    R, _ = procrustes(src, src * np.array([1.0, 1.0, -1.0]))
    assert np.isclose(np.linalg.det(R), 1.0)
    assert fit_residual(src, src * np.array([1.0, 1.0, -1.0])) > 0.1
    fit32 = procrustes(src.astype(np.float32), dst)
    for a, b in zip(fit32, procrustes(src.astype(np.float32).astype(np.float64), dst), strict=True):
        assert a.dtype == np.float64 and np.array_equal(a, b)
    bad = np.stack([dst, dst])
    bad[1, 3, 0] = np.nan
    R, t = procrustes(src, bad)
    assert np.isfinite(R[0]).all() and np.isnan(R[1]).all() and np.isnan(t[1]).all()
    assert np.isfinite(fit_residual(src, bad)[0]) and np.isnan(fit_residual(src, bad)[1])
    with pytest.raises(ValueError, match="points must be"):
        procrustes(src[:, :2], dst)


@pytest.mark.parametrize("points", [2, 9])
def test_numpy_solver_picks_the_optimal_rotation_closest_to_the_identity(points):
    """Two points, or points on a line, leave the rotation about that line
    free: every such rotation fits equally well, and the NumPy solver returns
    the one closest to the identity (largest trace), found here by a search
    over the free angle."""
    rng = np.random.default_rng(points)
    direction = rng.normal(size=3)
    src = np.outer(rng.normal(size=points), direction)
    R_true = _rot(rng.normal(size=3), 2.0).numpy()
    dst = src @ R_true.T + 0.5
    R, t = procrustes(src, dst)
    assert np.isclose(np.linalg.det(R), 1.0) and fit_residual(src, dst, R=R, t=t) < 1e-9
    axis = R_true @ direction / np.linalg.norm(direction)
    candidates = [_rot(axis, a).numpy() @ R_true for a in np.linspace(-math.pi, math.pi, 3601)]
    assert np.trace(R) >= max(np.trace(c) for c in candidates) - 1e-6


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    n=st.integers(4, 40),
    angle=st.floats(0.0, math.pi),
    shift=st.floats(-100.0, 100.0),
    log_scale=st.floats(-4.0, 3.0),
)
def test_property_recovers_rigid_transform(seed, n, angle, shift, log_scale):
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    R_true = _rot(axis / np.linalg.norm(axis), angle)
    src = torch.as_tensor(rng.normal(size=(n, 3)) * 10.0**log_scale)
    dst = src @ R_true.T + shift
    R, t = weighted_procrustes(src, dst)
    _check_rotation(R)
    assert float((R - R_true).abs().max()) < 1e-6
    assert float(rigid_fit_residual(src, dst, R=R, t=t)) < 1e-6 * (1.0 + abs(shift) + 10.0**log_scale)


# What the rigid_init, refine and grouping_quality stages import, and one
# batched solve (canonical points against two frames).
RIGID_STAGE_IMPORTS = """
import sys
import numpy as np
from mogaf.grouping.quality import run_grouping_quality_stage
from mogaf.grouping.stage import rigid_init
from mogaf.rigid import weighted_procrustes
src = np.random.default_rng(0).normal(size=(5, 3))
R, t = weighted_procrustes(src, np.stack([src + 1.0, src - 1.0]), np.ones((1, 5)))
print(tuple(R.shape), tuple(t.shape), ",".join(m for m in ("sympy", "scipy.spatial") if m in sys.modules) or "none")
"""


def test_rigid_stages_load_neither_sympy_nor_kd_trees():
    """A batched solve broadcasts its shapes without torch's symbolic-shape
    machinery (sympy, ~0.4 s a process), and the stages that only read groups
    do not load the grouping methods' k-d trees (scipy.spatial, ~0.25 s)."""
    res = subprocess.run([sys.executable, "-c", RIGID_STAGE_IMPORTS], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.split() == ["(2,", "3,", "3)", "(2,", "3)", "none"]
