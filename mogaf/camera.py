"""Camera conventions used everywhere in mogaf.

- Extrinsics are world-to-camera 4x4 matrices in the OpenCV convention:
  x right, y down, z forward (points in front of the camera have z > 0).
- Intrinsics K are 3x3, in pixels of the stored resolution.
- Continuous image coordinates: pixel (col i, row j) covers [i, i+1) x [j, j+1),
  so its centre is at (i + 0.5, j + 0.5). This is the convention of DyCheck,
  D-NeRF (cx = W/2 is the image centre) and gsplat, and it makes integer
  downscaling exact: K' = diag(1/s, 1/s, 1) K.
"""

from __future__ import annotations

import numpy as np

# OpenGL/Blender camera axes (x right, y up, z backward) to OpenCV axes.
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float, skew: float = 0.0) -> np.ndarray:
    return np.array([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)


def scale_intrinsics(K: np.ndarray, factor: float) -> np.ndarray:
    """Intrinsics of an image resized by `factor` (e.g. 0.5 for 2x smaller)."""
    out = np.array(K, dtype=np.float64, copy=True)
    out[..., :2, :] *= factor
    return out


def rigid_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid 4x4 transforms (batched), exact for orthonormal R."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def w2c_from_orientation_position(orientation: np.ndarray, position: np.ndarray) -> np.ndarray:
    """DyCheck/Nerfies cameras: orientation is the w2c rotation, position the centre."""
    R = np.asarray(orientation, dtype=np.float64)
    c = np.asarray(position, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ c
    return T


def camera_centers(w2c: np.ndarray) -> np.ndarray:
    """Camera centres in world coordinates for (..., 4, 4) w2c."""
    R = w2c[..., :3, :3]
    t = w2c[..., :3, 3]
    return -np.einsum("...ji,...j->...i", R, t)


def pose_problem(w2c: np.ndarray, tol: float = 1e-4) -> str | None:
    """Why a 4x4 world-to-camera matrix is not a rigid pose, or None if it is."""
    T = np.asarray(w2c, dtype=np.float64)
    if T.shape != (4, 4):
        return f"pose has shape {T.shape}, expected (4, 4)"
    if not np.all(np.isfinite(T)):
        return "pose has non-finite entries"
    if not np.allclose(T[3], [0, 0, 0, 1], atol=tol):
        return "pose bottom row is not [0, 0, 0, 1]"
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=tol):
        return "pose rotation is not orthonormal (non-invertible or scaled pose)"
    if np.linalg.det(R) < 0:
        return "pose rotation has determinant -1 (a reflection)"
    return None


# A camera centre farther than this from the others, in units of the scene's
# extent (the larger of the centres' spread and their distance from the
# origin), is a broken pose, not a far camera; beyond MAX_CAMERA_CENTRE no
# float32 renderer can place a pixel.
MAX_CAMERA_OUTLIER = 1e3
MAX_CAMERA_CENTRE = 1e8


def camera_centre_problem(w2c: np.ndarray) -> tuple[int, str] | None:
    """(frame, why) for the first camera centre of an (F, 4, 4) stack of
    rigid world-to-camera poses that no scene could have, or None."""
    T = np.asarray(w2c, dtype=np.float64)
    R, t = T[:, :3, :3], T[:, :3, 3]
    with np.errstate(over="ignore", invalid="ignore"):
        centres = -np.einsum("fji,fj->fi", R, t)  # -R^T t
    largest = np.abs(centres).max(axis=1)  # no overflow, unlike a norm of 1e300
    for f in range(len(T)):
        if not np.isfinite(largest[f]) or largest[f] > MAX_CAMERA_CENTRE:
            return f, f"camera centre has a coordinate of {largest[f]:.3g} (at most {MAX_CAMERA_CENTRE:.0e})"
    dist = np.linalg.norm(centres, axis=1)
    median = np.median(centres, axis=0)
    offset = np.linalg.norm(centres - median, axis=1)
    extent = max(float(np.median(offset)), float(np.median(dist)), 1e-6)
    f = int(np.argmax(offset))
    if offset[f] > MAX_CAMERA_OUTLIER * extent:
        return f, (
            f"camera centre lies {offset[f]:.3g} from the cameras' median centre, "
            f"{offset[f] / extent:.3g} times the scene's extent ({extent:.3g}); a broken pose"
        )
    return None


def project(points: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project world points (N, 3) to continuous pixel coordinates.

    Returns (uv (N, 2), depth (N,)); depth is the camera-space z. Points with
    z <= 0 get uv = nan-free values computed with a clamped z; callers mask
    them with depth > 0.
    """
    pts = np.asarray(points, dtype=np.float64)
    cam = pts @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[:, 2]
    zsafe = np.where(np.abs(z) < 1e-12, 1e-12, z)
    uvw = cam @ np.asarray(K, dtype=np.float64).T
    uv = uvw[:, :2] / zsafe[:, None]
    return uv, z
