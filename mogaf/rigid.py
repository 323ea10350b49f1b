"""Weighted Procrustes (Kabsch/Umeyama without scale) and rigid-fit residuals.

Differentiable, in torch (roma's solve): the structured forecaster's rigid
fits (procrustes_numpy) and refinement's rigid targets (apply_rigid). The
group stage (rigidity estimate) and the rigid_init stage (supplementary
"Group-wise Optimization": per rigid group and observed time, the SE(3) that
best maps canonical means to deformed means) solve the same problem in NumPy
(mogaf.rigid_fit) and never import torch.

Conventions: points are rows, dst ~= src @ R.T + t, i.e. y = R x + t.

Numerics
- All arithmetic runs in float64 (inputs of lower precision are promoted and
  the results cast back), so the functions are safe on float32 inputs.
- The rotation is the special-orthogonal polar factor of the weighted
  cross-covariance, computed by `roma.special_procrustes`: det(R) = +1 always,
  reflected point sets included.
- The cross-covariance is normalised by its Frobenius norm before the solve
  (the solution does not depend on the scale) so that roma's gradient damping
  (`gradient_eps`) is relative to the problem and not to the scene units.
- A tiny multiple of the identity (`IDENTITY_BIAS`, relative) is added so
  that when the problem has no unique answer (one point, all points
  identical, collinear points) the result is deterministic with finite
  gradients (roma's Horn solve does not resolve a gap this small, so among
  the optimal rotations it need not return the one closest to the identity;
  mogaf.rigid_fit's SVD does). Its effect on well-posed problems is of the
  order of 1e-12 rad.
- Weights are clamped at 0; weights that sum to zero fall back to uniform
  weights; an empty point set gives the identity and a zero translation.
"""

from __future__ import annotations

import numpy as np
import torch

# the same constants as the NumPy solver of the stages without torch
from .rigid_fit import IDENTITY_BIAS
from .rigid_fit import TINY as _TINY

GRADIENT_EPS = 1e-7


def _as_tensor(x) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x
    return torch.as_tensor(np.asarray(x))


def _result_dtype(*xs: torch.Tensor) -> torch.dtype:
    dtype = torch.float32
    for x in xs:
        if x is not None and x.is_floating_point():
            dtype = torch.promote_types(dtype, x.dtype)
    return dtype


def normalized_weights(weights: torch.Tensor | None, shape: tuple[int, ...], dtype=torch.float64) -> torch.Tensor:
    """Weights (..., P) summing to one; uniform where they are None or sum to 0."""
    P = shape[-1]
    if weights is None:
        return torch.full(shape, 1.0 / max(P, 1), dtype=dtype)
    w = torch.broadcast_to(weights.to(dtype), shape).clamp_min(0.0)
    total = w.sum(-1, keepdim=True)
    uniform = torch.full_like(w, 1.0 / max(P, 1))
    return torch.where(total > 0, w / total.clamp_min(1e-300), uniform)


def weighted_procrustes(src, dst, weights=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Rigid transform (R, t) minimising sum_p w_p |R src_p + t - dst_p|^2.

    src, dst: (..., P, 3) with broadcastable batch dimensions (e.g. canonical
    means (P, 3) against deformed means (T, P, 3)); weights: (..., P) or None.
    Returns R (..., 3, 3) with det = +1 and t (..., 3), differentiable with
    respect to src, dst and weights.
    """
    src_t, dst_t = _as_tensor(src), _as_tensor(dst)
    w_t = None if weights is None else _as_tensor(weights)
    out_dtype = _result_dtype(src_t, dst_t, w_t)
    if src_t.shape[-1] != 3 or dst_t.shape[-1] != 3:
        raise ValueError(f"points must be (..., P, 3), got {tuple(src_t.shape)} and {tuple(dst_t.shape)}")
    x = src_t.to(torch.float64)
    y = dst_t.to(torch.float64)
    # numpy's shape rule: the same result as torch.broadcast_shapes, whose first call imports
    # torch's symbolic-shape machinery (sympy, ~0.4 s a process)
    batch = np.broadcast_shapes(x.shape[:-2], y.shape[:-2], () if w_t is None else w_t.shape[:-1])
    P = np.broadcast_shapes(x.shape[-2:-1], y.shape[-2:-1], () if w_t is None else w_t.shape[-1:])
    x = torch.broadcast_to(x, batch + P + (3,))
    y = torch.broadcast_to(y, batch + P + (3,))
    if P[0] == 0:
        R = torch.eye(3, dtype=torch.float64).expand(batch + (3, 3)).clone()
        t = torch.zeros(batch + (3,), dtype=torch.float64)
        # Keep the graph connected so callers can always call backward().
        link = x.sum() + y.sum() + (0.0 if w_t is None else w_t.to(torch.float64).sum())
        R = R + 0.0 * link
        return R.to(out_dtype), t.to(out_dtype)
    w = normalized_weights(w_t, batch + P)
    cx = torch.einsum("...p,...pi->...i", w, x)
    cy = torch.einsum("...p,...pi->...i", w, y)
    xc = x - cx[..., None, :]
    yc = y - cy[..., None, :]
    # M = sum_p w_p y_p x_p^T: the rotation maximising tr(R^T M) is its polar factor.
    M = torch.einsum("...p,...pi,...pj->...ij", w, yc, xc)
    scale = torch.sqrt((M * M).sum((-1, -2), keepdim=True) + _TINY)
    eye = torch.eye(3, dtype=torch.float64)
    Mn = M / scale + IDENTITY_BIAS * eye
    from .eager_roma import load as load_roma

    R = load_roma().special_procrustes(Mn.reshape(-1, 3, 3), gradient_eps=GRADIENT_EPS).reshape(batch + (3, 3))
    t = cy - torch.einsum("...ij,...j->...i", R, cx)
    return R.to(out_dtype), t.to(out_dtype)


def apply_rigid(R, t, points) -> torch.Tensor:
    """R (..., 3, 3), t (..., 3) applied to points (..., P, 3)."""
    R, t, points = _as_tensor(R), _as_tensor(t), _as_tensor(points)
    return torch.einsum("...ij,...pj->...pi", R, points) + t[..., None, :]


def rigid_fit_residual(src, dst, weights=None, R=None, t=None, *, squared: bool = False) -> torch.Tensor:
    """Weighted RMS distance between R src + t and dst, per batch element.

    If R and t are not given, the best rigid fit (weighted_procrustes) is
    used. Returns (...,); with squared=True the weighted mean squared
    distance instead (smooth everywhere, preferable inside losses).
    """
    src_t, dst_t = _as_tensor(src), _as_tensor(dst)
    w_t = None if weights is None else _as_tensor(weights)
    out_dtype = _result_dtype(src_t, dst_t, w_t)
    if R is None or t is None:
        R, t = weighted_procrustes(src_t, dst_t, w_t)
    R64, t64 = _as_tensor(R).to(torch.float64), _as_tensor(t).to(torch.float64)
    pred = apply_rigid(R64, t64, src_t.to(torch.float64))
    y = dst_t.to(torch.float64)
    pred, y = torch.broadcast_tensors(pred, y)
    d2 = ((pred - y) ** 2).sum(-1)
    if d2.shape[-1] == 0:
        ms = d2.sum(-1) + (0.0 if w_t is None else 0.0 * w_t.to(torch.float64).sum())
    else:
        w = normalized_weights(w_t, d2.shape)
        ms = (w * d2).sum(-1)
    if squared:
        return ms.to(out_dtype)
    # clamp_min keeps the gradient finite (zero) at an exact fit.
    return torch.sqrt(ms.clamp_min(1e-30)).to(out_dtype)


def procrustes_numpy(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """NumPy convenience wrapper (float64, no gradients)."""
    with torch.no_grad():
        R, t = weighted_procrustes(
            torch.as_tensor(np.asarray(src, dtype=np.float64)),
            torch.as_tensor(np.asarray(dst, dtype=np.float64)),
            None if weights is None else torch.as_tensor(np.asarray(weights, dtype=np.float64)),
        )
    return R.numpy(), t.numpy()
