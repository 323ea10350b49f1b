"""Interpolation over time steps: frames to steps, and steps without a frame.

fill_in_time (per-point values over frame times), interpolate_steps (linear
between the steps that have a value) and gap_interpolation (the natural
cubic-spline matrix that fills the steps without a frame from the knot
steps). Used by the initialisation, the silhouette fit and the trainer.
"""

from __future__ import annotations

import numpy as np

from ..errors import MogafError


def fill_in_time(xyz: np.ndarray, ok: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Linear interpolation of invalid entries over frame times (nearest at the ends)."""
    out = xyz.copy()
    order = np.argsort(times, kind="stable")
    tt = times[order].astype(np.float64)
    for p in range(xyz.shape[0]):
        okp = ok[p, order]
        if okp.all() or not okp.any():
            continue
        for d in range(3):
            vals = xyz[p, order, d]
            out[p, order, d] = np.interp(tt, tt[okp], vals[okp])
    return out


def interpolate_steps(values: np.ndarray, have: np.ndarray) -> np.ndarray:
    """(B, T, D) values defined where have (T,) is True; linear in between, nearest at the ends."""
    if have.all():
        return values
    if not have.any():
        raise MogafError("reconstruction init: no observed time step has a frame")
    T = values.shape[1]
    steps = np.arange(T)
    out = values.copy()
    for b in range(values.shape[0]):
        for d in range(values.shape[2]):
            out[b, :, d] = np.interp(steps, steps[have], values[b, have, d])
    return out


def gap_interpolation(num_steps: int, knots: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Steps without a frame, and the (gaps, K) matrix that fills them from the K knot steps.

    Natural cubic spline through the knots (linear in the knot values) inside
    [first knot, last knot], the end knot's value outside. None if every step
    is a knot.
    """
    from scipy.interpolate import CubicSpline

    knots = np.unique(np.asarray(knots, dtype=np.int64))
    gaps = np.setdiff1d(np.arange(num_steps), knots)
    if gaps.size == 0:
        return None
    K = knots.size
    M = np.zeros((gaps.size, K))
    inside = (gaps > knots[0]) & (gaps < knots[-1])
    if K >= 3:
        cs = CubicSpline(knots.astype(float), np.eye(K), axis=0, bc_type="natural")
        M[inside] = cs(gaps[inside].astype(float))
    elif K == 2:
        w = (gaps[inside] - knots[0]) / (knots[1] - knots[0])
        M[inside, 0], M[inside, 1] = 1 - w, w
    M[gaps <= knots[0], 0] = 1.0
    M[gaps >= knots[-1], K - 1] = 1.0
    return gaps, M
