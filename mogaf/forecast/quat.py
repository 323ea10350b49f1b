"""Float64 quaternion helpers (scalar-first, wxyz) for the forecasters.

Everything works on numpy arrays with the quaternion on the last axis and
broadcasts over leading axes. Rotations are exact (Hamilton product, rotation
of a vector by q v q*); results are renormalised where they are fed back.
"""

from __future__ import annotations

import numpy as np


def normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternions; a zero one (no rotation to keep) becomes the identity,
    as `mogaf.representation.normalize_quat` makes it."""
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    unit = q / np.where(n > 0.0, n, 1.0)
    return np.where(n > 0.0, unit, np.array([1.0, 0.0, 0.0, 0.0]))


def conj(q: np.ndarray) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    return np.concatenate([q[..., :1], -q[..., 1:]], axis=-1)


def mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b (apply b first, then a)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v (..., 3) by unit quaternions q (..., 4)."""
    q = np.asarray(q, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def from_axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    half = 0.5 * np.asarray(angle, dtype=np.float64)[..., None]
    return np.concatenate([np.cos(half), np.sin(half) * axis], axis=-1)


def canonical_sign(q: np.ndarray) -> np.ndarray:
    """Pick the representative of {q, -q} with w > 0 (ties broken on x, y, z)."""
    q = np.asarray(q, dtype=np.float64)
    sign = np.zeros(q.shape[:-1])
    for k in range(4):
        comp = q[..., k]
        undecided = sign == 0
        sign = np.where(undecided & (comp > 0), 1.0, sign)
        sign = np.where(undecided & (comp < 0), -1.0, sign)
    sign = np.where(sign == 0, 1.0, sign)
    return q * sign[..., None]


def make_continuous(q: np.ndarray, axis: int = -2) -> np.ndarray:
    """Sign continuity along time: the first quaternion gets the canonical sign,
    each later one is flipped when dot(q_t, q_{t-1}) < 0.

    Negating any subset of the input quaternions gives a bit-identical result,
    so every method built on this is invariant to q -> -q in its input.
    """
    q = np.moveaxis(np.array(q, dtype=np.float64, copy=True), axis, 0)
    q[0] = canonical_sign(q[0])
    for t in range(1, q.shape[0]):
        d = np.sum(q[t] * q[t - 1], axis=-1)
        # dot == 0 exactly is ambiguous; fall back to the canonical sign there so
        # the choice still does not depend on the input's sign.
        flip = d < 0
        tie = d == 0
        cur = np.where(flip[..., None], -q[t], q[t])
        cur = np.where(tie[..., None], canonical_sign(q[t]), cur)
        q[t] = cur
    return np.moveaxis(q, 0, axis)


def align_to(q: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Flip q where dot(q, ref) < 0 (continuity with a reference)."""
    d = np.sum(q * ref, axis=-1, keepdims=True)
    return np.where(d < 0, -q, q)


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Geodesic angle (radians) between rotations a and b, sign-invariant."""
    rel = mul(conj(normalize(a)), normalize(b))
    # atan2 form: accurate near 0 (arccos of the dot product is not).
    return 2.0 * np.arctan2(np.linalg.norm(rel[..., 1:], axis=-1), np.abs(rel[..., 0]))


def to_rotvec(q: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) of unit quaternions: axis * angle, angle in
    [0, pi] (the w >= 0 representative). atan2 keeps it accurate near 0 and pi."""
    q = normalize(q)
    q = np.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., :1])
    # angle / s -> 2 / w as s -> 0 (w -> 1): no 0/0 for the identity.
    factor = np.where(s > 1e-12, angle / np.where(s > 1e-12, s, 1.0), 2.0 / np.maximum(q[..., :1], 1e-12))
    return v * factor


def from_rotvec(r: np.ndarray) -> np.ndarray:
    """Unit quaternions (wxyz) of rotation vectors (..., 3); exact inverse of
    to_rotvec for angles below pi."""
    r = np.asarray(r, dtype=np.float64)
    angle = np.linalg.norm(r, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(a/2)/a -> 1/2 - a^2/48 near 0 (series avoids 0/0).
    small = angle < 1e-6
    sinc = np.where(small, 0.5 - angle * angle / 48.0, np.sin(half) / np.where(small, 1.0, angle))
    return normalize(np.concatenate([np.cos(half), r * sinc], axis=-1))
