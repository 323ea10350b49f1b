"""Rotation and trajectory helpers of the structured MoGaF forecaster
(mogaf.forecast.structured): accumulated rotation vectors, a group's best
rigid motion, its still members, its rigid parts and local polynomial fits."""

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
    from mogaf.representation import matrix_to_quat_numpy  # local: it imports h5py (artefacts)
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
    return centroids, quat.make_continuous(matrix_to_quat_numpy(R), axis=0), rel


def rigid_parts(positions: np.ndarray, k: int, seed: int, iterations: int = 8) -> np.ndarray:
    """(G,) labels 0..P-1 (P <= k) of a group's members (G, T, 3), each part
    moving as one rigid body (K-motions): k-means on the members'
    displacements from their last position, then, alternately, each part's
    best rigid motion from the last frame to every frame and each member moved
    to the part whose motion follows its trajectory closest (at most
    `iterations` rounds). A part of fewer than 3 members fixes no rotation:
    the next round moves its members to the other parts (a part the last
    round left that small is forecast per Gaussian). Deterministic for a seed."""
    from sklearn.cluster import KMeans

    pos = np.asarray(positions, dtype=np.float64)
    G = pos.shape[0]
    displacement = (pos - pos[:, -1:]).reshape(G, -1)
    # (k-means needs k distinct points: members moving alike count once)
    k = min(int(k), G // 3, len(np.unique(displacement, axis=0)))
    if k <= 1:
        return np.zeros(G, np.int64)
    labels = KMeans(k, n_init=4, random_state=int(seed)).fit_predict(displacement).astype(np.int64)
    for _ in range(int(iterations)):
        errors = np.stack([_rigid_fit_error(pos, labels == p) for p in range(k)])
        if not np.isfinite(errors).any(axis=0).all():
            break
        new = np.argmin(errors, axis=0)
        if np.array_equal(new, labels):
            break
        labels = new
    _, labels = np.unique(labels, return_inverse=True)
    return labels.astype(np.int64)


def unexplained_motion(positions: np.ndarray, labels: np.ndarray) -> float:
    """The share of a group's motion (G, T, 3) its rigid parts (`labels`,
    rigid_parts) leave unexplained: the RMS over members and frames of each
    member's distance from its part's rigid fit, over the RMS of its
    displacement from its last position (0: the parts move exactly as rigid
    bodies; about 0.5: members each moving on their own)."""
    pos = np.asarray(positions, dtype=np.float64)
    error = np.zeros(pos.shape[0])
    for p in range(int(labels.max()) + 1):
        part = labels == p
        error[part] = _rigid_fit_error(pos, part)[part] if part.sum() >= 3 else 0.0
    displacement = np.sqrt(np.mean(np.sum((pos - pos[:, -1:]) ** 2, axis=-1), axis=1))
    moved = float(np.sqrt(np.mean(displacement**2)))
    return float(np.sqrt(np.mean(error**2)) / moved) if moved > 0 else 0.0


def _rigid_fit_error(pos: np.ndarray, part: np.ndarray) -> np.ndarray:
    """(G,) each member's RMS distance over the frames from where the best rigid
    motion of `part`'s members (from the last frame to every frame) carries
    its last position; inf for every member when the part has fewer than 3."""
    from mogaf.rigid import procrustes_numpy  # local: mogaf.rigid imports torch at module level

    if part.sum() < 3:
        return np.full(pos.shape[0], np.inf)
    members = pos[part]
    R, t = procrustes_numpy(members[:, -1][None], np.moveaxis(members, 1, 0))  # (T, 3, 3), (T, 3)
    carried = np.einsum("tij,gj->gti", R, pos[:, -1]) + t[None]
    return np.sqrt(np.mean(np.sum((carried - pos) ** 2, axis=-1), axis=1))


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


def _window_fit(series: np.ndarray, window: int, degree: int) -> tuple[np.ndarray, float]:
    """Each row's least-squares polynomial of `degree` through the last
    `window` values of `series` (S, T) (of lower degree when fewer values are
    there): its coefficients (degree' + 1, S) in time measured in units of the
    window, last value at 0 (a well-conditioned design), and that unit in steps."""
    values = np.asarray(series, dtype=np.float64)
    W = min(int(window), values.shape[1])
    degree = min(int(degree), W - 1)
    unit = max(W - 1, 1)
    t = np.arange(-W + 1, 1, dtype=np.float64) / unit
    design = np.vander(t, degree + 1, increasing=True)  # (W, degree + 1)
    coef, *_ = np.linalg.lstsq(design, values[:, -W:].T, rcond=None)  # (degree + 1, S)
    return coef, float(unit)


def local_polynomial(series: np.ndarray, window: int, degree: int, n_steps: int) -> np.ndarray:
    """(S, n_steps) values after the end of `series` (S, T) on each row's
    least-squares polynomial of `degree` (1: a line, 2: a parabola) through
    its last `window` values (of lower degree when fewer values are there:
    a line through two, the last value repeated with one). The fit, not the
    last value, starts the forecast: a fit through several values is less
    moved by the error of the last frame than a velocity taken from two."""
    coef, unit = _window_fit(series, window, degree)
    future = np.arange(1, n_steps + 1, dtype=np.float64) / unit
    return (np.vander(future, coef.shape[0], increasing=True) @ coef).T


def braking_polynomial(series: np.ndarray, window: int, n_steps: int) -> np.ndarray:
    """(S, n_steps) values after the end of `series` (S, T), S a multiple of 3:
    each triple of rows is one vector (a centroid, a rotation vector, a
    Gaussian's position). From its least-squares parabola through the last
    `window` values it takes the end value p, velocity v and acceleration a;
    where a slows the vector down (a . v < 0) it decelerates uniformly along v
    by -a . v/|v| until it stops, then holds; otherwise it keeps the constant
    velocity v. A body that brakes or rolls to rest stops instead of
    overshooting, and one that speeds up is not carried faster than it was
    seen to move; a thrown body is held at the top of its throw, and a
    collision ends a deceleration the fit cannot see coming."""
    S = series.shape[0]
    if S % 3:
        raise ValueError(f"braking_polynomial needs rows in triples, got {S}")
    coef, unit = _window_fit(series, window, 2)
    coef = np.vstack([coef, np.zeros((3 - coef.shape[0], coef.shape[1]))])  # a line or a value: no curvature
    p, v, a = (x.reshape(-1, 3) for x in (coef[0], coef[1] / unit, 2.0 * coef[2] / unit**2))
    speed = np.linalg.norm(v, axis=-1)
    direction = v / np.where(speed > 0, speed, 1.0)[:, None]
    slowing = np.maximum(-np.sum(a * direction, axis=-1), 0.0)  # deceleration along v, >= 0
    # stopping time; inf where not slowing (then s = u: constant velocity)
    stop = np.where(slowing > 0, speed / np.where(slowing > 0, slowing, 1.0), np.inf)
    u = np.arange(1, n_steps + 1, dtype=np.float64)[None, :]  # (1, n)
    s = np.minimum(u, stop[:, None])
    travelled = speed[:, None] * s - 0.5 * slowing[:, None] * s**2  # (V, n)
    out = p[:, None, :] + travelled[..., None] * direction[:, None, :]  # (V, n, 3)
    return out.transpose(0, 2, 1).reshape(S, n_steps)


def braking_polynomial_reference(series: np.ndarray, window: int, n_steps: int) -> np.ndarray:
    """braking_polynomial one vector and one step at a time (the slow reference its tests compare with)."""
    values = np.asarray(series, dtype=np.float64)
    W = min(int(window), values.shape[1])
    out = np.zeros((values.shape[0], n_steps))
    t = np.arange(-W + 1, 1, dtype=np.float64)
    for r in range(0, values.shape[0], 3):
        if W >= 3:
            c2, c1, c0 = np.stack([np.polyfit(t, values[r + i, -W:], 2) for i in range(3)], axis=1)
        elif W == 2:
            c1, c0 = np.stack([np.polyfit(t, values[r + i, -W:], 1) for i in range(3)], axis=1)
            c2 = np.zeros(3)
        else:
            c0, c1, c2 = values[r : r + 3, -1], np.zeros(3), np.zeros(3)
        v, acc = c1, 2.0 * c2
        speed = float(np.linalg.norm(v))
        for k in range(n_steps):
            u = k + 1.0
            if speed == 0.0:
                x = c0
            else:
                d = v / speed
                dec = max(-float(acc @ d), 0.0)
                if dec > 0.0:
                    s = min(u, speed / dec)
                    x = c0 + d * (speed * s - 0.5 * dec * s * s)
                else:
                    x = c0 + v * u
            out[r : r + 3, k] = x
    return out
