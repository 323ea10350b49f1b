"""Weighted Procrustes and rigid-fit residuals in NumPy, for the stages that
never load torch (group, rigid_init: importing torch is about a second of
each of those jobs).

The same problem, conventions and numerics as mogaf.rigid (points are rows,
y = R x + t; float64; weights clamped at 0, a zero total falls back to
uniform; the cross-covariance normalised by its Frobenius norm plus
IDENTITY_BIAS times the identity). mogaf.rigid solves with roma (Horn's
quaternion method) and is differentiable; this module solves the same
normalised problem by an SVD, without gradients. The two agree to float64
rounding wherever the fit has one answer (tests/test_rigid.py). Where it has
many (two points, points on a line), the SVD resolves the identity bias and
returns the optimal rotation closest to the identity; roma's Horn solve does
not resolve so small a gap (roma's own note) and returns another optimal one.
Non-finite points give NaN poses and residuals, as mogaf.rigid does.
"""

from __future__ import annotations

import numpy as np

IDENTITY_BIAS = 1e-12  # relative; its effect on a well-posed fit is of the order of 1e-12 rad
TINY = 1e-200  # added under square roots (representable in float64)


def normalized_weights(weights: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray:
    """Weights broadcast to `shape` (..., P), clamped at 0, summing to 1 over
    the last axis; uniform where they sum to 0 (or where none are given)."""
    P = shape[-1]
    uniform = np.full(shape, 1.0 / max(P, 1))
    if weights is None:
        return uniform
    w = np.clip(np.broadcast_to(np.asarray(weights, dtype=np.float64), shape), 0.0, None)
    total = w.sum(-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0, w / np.maximum(total, 1e-300), uniform)


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation R (det +1) maximising tr(R^T M), for M (..., 3, 3): the
    special-orthogonal polar factor U diag(1, 1, det(U V^T)) V^T."""
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    return (U * np.concatenate([np.ones(d.shape + (2,)), d[..., None]], axis=-1)[..., None, :]) @ Vt


def procrustes(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) minimising sum_p w_p |R src_p + t - dst_p|^2, float64.

    src, dst: (..., P, 3) with broadcastable batch dimensions; weights (..., P)
    or None. Returns R (..., 3, 3) with det = +1 and t (..., 3); the identity
    and a zero translation for an empty point set."""
    x = np.asarray(src, dtype=np.float64)
    y = np.asarray(dst, dtype=np.float64)
    if x.shape[-1] != 3 or y.shape[-1] != 3:
        raise ValueError(f"points must be (..., P, 3), got {x.shape} and {y.shape}")
    w_shape = () if weights is None else np.shape(weights)
    batch = np.broadcast_shapes(x.shape[:-2], y.shape[:-2], w_shape[:-1])
    P = np.broadcast_shapes(x.shape[-2:-1], y.shape[-2:-1], w_shape[-1:])
    x = np.broadcast_to(x, batch + P + (3,))
    y = np.broadcast_to(y, batch + P + (3,))
    if P[0] == 0:
        return np.broadcast_to(np.eye(3), batch + (3, 3)).copy(), np.zeros(batch + (3,))
    w = normalized_weights(weights, batch + P)
    cx = np.einsum("...p,...pi->...i", w, x)
    cy = np.einsum("...p,...pi->...i", w, y)
    xc = x - cx[..., None, :]
    yc = y - cy[..., None, :]
    M = np.einsum("...p,...pi,...pj->...ij", w, yc, xc)
    scale = np.sqrt((M * M).sum((-1, -2), keepdims=True) + TINY)
    Mn = M / scale + IDENTITY_BIAS * np.eye(3)
    # LAPACK's SVD fails on non-finite input: NaN poses there (as torch's solve gives)
    bad = ~np.isfinite(Mn).all((-1, -2))
    R = nearest_rotation(np.where(bad[..., None, None], np.eye(3), Mn))
    R = np.where(bad[..., None, None], np.nan, R)
    t = cy - np.einsum("...ij,...j->...i", R, cx)
    return R, t


def fit_residual(
    src: np.ndarray,
    dst: np.ndarray,
    weights: np.ndarray | None = None,
    R: np.ndarray | None = None,
    t: np.ndarray | None = None,
    *,
    squared: bool = False,
) -> np.ndarray:
    """Weighted RMS distance between R src + t and dst per batch element
    (...,), float64; the best fit (procrustes) when R and t are not given.
    squared=True: the weighted mean squared distance instead."""
    x = np.asarray(src, dtype=np.float64)
    y = np.asarray(dst, dtype=np.float64)
    if R is None or t is None:
        R, t = procrustes(x, y, weights)
    pred = np.einsum("...ij,...pj->...pi", np.asarray(R, np.float64), x) + np.asarray(t, np.float64)[..., None, :]
    pred, y = np.broadcast_arrays(pred, y)
    d2 = ((pred - y) ** 2).sum(-1)
    ms = (normalized_weights(weights, d2.shape) * d2).sum(-1) if d2.shape[-1] else d2.sum(-1)
    return ms if squared else np.sqrt(np.maximum(ms, 1e-30))
