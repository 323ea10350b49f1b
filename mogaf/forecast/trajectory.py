"""Rotation and trajectory helpers of the structured MoGaF forecaster
(mogaf.forecast.structured): accumulated rotation vectors, a group's best
rigid motion, its still members and local polynomial fits."""

from __future__ import annotations

import numpy as np

from mogaf.forecast import quat


def accumulated_rotvec(q: np.ndarray) -> np.ndarray:
    """(..., T, 4) unit quaternions -> (..., T, 3): the sum of the body-frame
    rotation vectors of the steps so far (0 at the first frame). Unlike the
    rotation vector of the pose itself it never wraps at pi, so a spin of many
    turns is a straight line."""
    q = quat.make_continuous(q, axis=-2)
    steps = quat.to_rotvec(quat.mul(quat.conj(q[..., :-1, :]), q[..., 1:, :]))
    out = np.zeros(q.shape[:-1] + (3,))
    out[..., 1:, :] = np.cumsum(steps, axis=-2)
    return out


def integrate_rotvec(q_last: np.ndarray, r_last: np.ndarray, r_future: np.ndarray) -> np.ndarray:
    """Quaternions (..., n, 4) continuing q_last (..., 4) along the accumulated
    rotation vectors r_future (..., n, 3) that follow r_last (..., 3)."""
    steps = np.diff(np.concatenate([r_last[..., None, :], r_future], axis=-2), axis=-2)
    out = np.empty(r_future.shape[:-1] + (4,))
    q = quat.normalize(q_last)
    for k in range(steps.shape[-2]):
        q = quat.normalize(quat.mul(q, quat.from_rotvec(steps[..., k, :])))
        out[..., k, :] = q
    return out


def rigid_decomposition(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Best rigid motion of a group (G, T, 3) from its last frame to every frame.

    Returns centroids (T, 3), rotations (T, 4) wxyz with the identity at the
    last frame, and the relative residual: the largest per-frame RMS distance
    of the members from the rigid fit, over the group's RMS radius."""
    from mogaf.rigid import procrustes_numpy  # local: mogaf.rigid imports torch at module level

    pos = np.asarray(positions, dtype=np.float64)
    ref = pos[:, -1]
    centroids = pos.mean(axis=0)
    src = np.repeat((ref - centroids[-1])[None], pos.shape[1], axis=0)
    dst = np.moveaxis(pos, 1, 0) - centroids[:, None, :]
    R, _ = procrustes_numpy(src, dst)
    fitted = np.einsum("tij,tgj->tgi", R, src)
    residual = np.sqrt(np.mean(np.sum((fitted - dst) ** 2, axis=-1), axis=1))
    radius = float(np.sqrt(np.mean(np.sum(src[0] ** 2, axis=-1))))
    rel = float(residual.max() / radius) if radius > 0 else 0.0
    return centroids, quat.make_continuous(_matrix_to_quat(R), axis=0), rel


def _matrix_to_quat(R: np.ndarray) -> np.ndarray:
    import torch  # local: only this path computes with it

    from mogaf.representation import matrix_to_quat

    return matrix_to_quat(torch.from_numpy(np.ascontiguousarray(R, dtype=np.float64))).numpy()


def _noise_level(series: np.ndarray) -> float:
    """Jitter of (G, T, 3) trajectories: the median over the group of each
    one's median third difference. Motion of constant acceleration has none,
    white noise of deviation s about 4.5 s (a norm of 3 components)."""
    return float(np.median(np.median(np.linalg.norm(np.diff(series, n=3, axis=1), axis=-1), axis=1)))


def still_gaussians(positions: np.ndarray, factor: float, quats: np.ndarray | None = None) -> np.ndarray:
    """(G,) True where a Gaussian's observed motion is below the noise level:
    it never moves further from its last position (and, with `quats`, never
    turns further from its last orientation) than factor x the group's jitter."""
    pos = np.asarray(positions, dtype=np.float64)
    if pos.shape[1] < 4:
        return np.zeros(pos.shape[0], bool)
    still = np.linalg.norm(pos - pos[:, -1:], axis=-1).max(axis=1) <= factor * _noise_level(pos)
    if quats is not None:
        rv = accumulated_rotvec(np.asarray(quats, dtype=np.float64))
        still &= np.linalg.norm(rv - rv[:, -1:], axis=-1).max(axis=1) <= factor * _noise_level(rv)
    return still


def rigid_group_still(positions: np.ndarray, factor: float) -> np.ndarray:
    """(G,) the still members of a rigid group: still_gaussians on positions
    (the reconstruction turns a joined resting part with the body), and none
    unless at least 3 members move, so a moving body remains: a fast turn's own
    third differences (the jitter estimate) can exceed every member's reach."""
    still = still_gaussians(positions, factor)
    if (~still).sum() < 3:
        still[:] = False
    return still


def local_polynomial(series: np.ndarray, window: int, degree: int, n_steps: int) -> np.ndarray:
    """(S, n_steps) values after the end of `series` (S, T) on each row's
    least-squares polynomial of `degree` (1: a line, 2: a parabola) through
    its last `window` values (of lower degree when fewer values are there:
    a line through two, the last value repeated with one). The fit, not the
    last value, starts the forecast: a fit through several values is less
    moved by the error of the last frame than a velocity taken from two."""
    values = np.asarray(series, dtype=np.float64)
    W = min(int(window), values.shape[1])
    degree = min(int(degree), W - 1)
    # time in units of the window, last value at 0: a well-conditioned design
    t = np.arange(-W + 1, 1, dtype=np.float64) / max(W - 1, 1)
    design = np.vander(t, degree + 1, increasing=True)  # (W, degree + 1)
    coef, *_ = np.linalg.lstsq(design, values[:, -W:].T, rcond=None)  # (degree + 1, S)
    future = np.arange(1, n_steps + 1, dtype=np.float64) / max(W - 1, 1)
    return (np.vander(future, degree + 1, increasing=True) @ coef).T
