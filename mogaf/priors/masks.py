"""Foreground masks when the dataset ships none.

- `motion_segmentation`: pixels whose flow (to the previous and to the next
  observed frame) disagrees with the camera-induced motion. The camera motion
  is a RANSAC homography fitted to the flow (`motion_camera_model`
  "homography"), a fundamental matrix (Sampson distance, "fundamental": for
  translating cameras with parallax), or zero ("none": static camera). A pixel
  is moving when both residuals exceed `motion_threshold_px` (one at the ends
  of the video); the mask is cleaned with an opening, small components
  (< `motion_min_area` of the image) are dropped, holes are filled and it is
  dilated by `motion_dilate_px`. An object that stops moving disappears.
  `static_tracks` then tells which tracks inside such a mask do not move
  beyond the camera motion (the mask bleeds around moving objects): the
  stage drops them from the instances and the mask.
- `background_colour_mask`: for composited synthetic renders (D-NeRF without
  alpha), pixels that differ from the known background colour.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from ..errors import MogafError
from .params import load_settings

CAMERA_MODELS = ("homography", "fundamental", "none")


@dataclass
class CameraMotion:
    """Camera-induced motion between two frames: a fitted model or none."""

    kind: str  # "homography" | "fundamental" | "none"
    matrix: np.ndarray | None = None

    def residual(self, x0: np.ndarray, x1: np.ndarray) -> np.ndarray:
        """Distance (px) of the correspondences x0 -> x1 (N, 2) from the camera motion."""
        x0 = np.asarray(x0, np.float64)
        x1 = np.asarray(x1, np.float64)
        if self.kind == "none" or self.matrix is None:
            return np.linalg.norm(x1 - x0, axis=-1)
        h0 = np.concatenate([x0, np.ones(x0.shape[:-1] + (1,))], -1)
        if self.kind == "homography":
            pts = h0 @ self.matrix.T
            pred = pts[..., :2] / np.where(np.abs(pts[..., 2:]) < 1e-9, 1e-9, pts[..., 2:])
            return np.linalg.norm(x1 - pred, axis=-1)
        h1 = np.concatenate([x1, np.ones(x1.shape[:-1] + (1,))], -1)
        Fx0 = h0 @ self.matrix.T
        Ftx1 = h1 @ self.matrix
        num = np.abs(np.sum(h1 * Fx0, -1))
        den = np.sqrt(Fx0[..., 0] ** 2 + Fx0[..., 1] ** 2 + Ftx1[..., 0] ** 2 + Ftx1[..., 1] ** 2) + 1e-9
        return num / den


def fit_camera_motion(flow: np.ndarray, model: str, stride: int = 4) -> CameraMotion:
    """RANSAC fit of the camera-induced motion to a dense flow (array coordinates)."""
    if model == "none":
        return CameraMotion("none")
    H, W = flow.shape[:2]
    ys, xs = np.mgrid[0:H:stride, 0:W:stride]
    src = np.stack([xs.ravel(), ys.ravel()], -1).astype(np.float32)
    dst = src + flow[ys.ravel(), xs.ravel()]
    if len(src) < 8:
        return CameraMotion("none")
    if model == "homography":
        M, inl = cv2.findHomography(src, dst, cv2.RANSAC, 1.0, maxIters=500, confidence=0.99)
        ok = M is not None and inl is not None and inl.mean() >= 0.2
    else:
        M, inl = cv2.findFundamentalMat(src, dst, cv2.FM_RANSAC, 1.0, 0.99)
        ok = M is not None and M.shape == (3, 3) and inl is not None and inl.mean() >= 0.2
    # Too few pixels agree on a camera motion: fall back to a static camera.
    return CameraMotion(model, np.asarray(M, np.float64)) if ok else CameraMotion("none")


def _camera_residual(flow: np.ndarray, cam: CameraMotion) -> np.ndarray:
    """Per-pixel residual (px) of `flow` after removing the camera motion."""
    H, W = flow.shape[:2]
    gy, gx = np.mgrid[0:H, 0:W].astype(np.float64)
    x0 = np.stack([gx, gy], -1)
    return cam.residual(x0, x0 + flow).astype(np.float32)


def clean_mask(mask: np.ndarray, min_area: float, dilate_px: int) -> np.ndarray:
    H, W = mask.shape
    m = mask.astype(np.uint8)
    m = cv2.morphologyEx(m, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    n, lab, st, _ = cv2.connectedComponentsWithStats(m, connectivity=8)
    keep = np.zeros(n, bool)
    keep[1:] = st[1:, cv2.CC_STAT_AREA] >= max(1.0, min_area * H * W)
    m = keep[lab].astype(np.uint8)
    # Fill holes: background not connected to the border becomes foreground.
    inv = (1 - m).astype(np.uint8)
    n2, lab2 = cv2.connectedComponents(inv, connectivity=4)
    border = np.unique(np.concatenate([lab2[0], lab2[-1], lab2[:, 0], lab2[:, -1]]))
    hole = (inv > 0) & ~np.isin(lab2, border)
    m[hole] = 1
    if dilate_px > 0:
        k = 2 * int(dilate_px) + 1
        m = cv2.dilate(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    return m.astype(bool)


def motion_segmentation(
    fwd: np.ndarray, bwd: np.ndarray, params: Mapping[str, Any]
) -> tuple[np.ndarray, list[CameraMotion]]:
    """(T, H, W) bool moving-pixel masks from consecutive flows (T-1, H, W, 2),
    and the camera motion fitted to each forward flow t -> t+1."""
    params = load_settings(params)
    model = str(params.motion_camera_model).lower()
    if model not in CAMERA_MODELS:
        raise MogafError(f"priors: motion_camera_model {model!r} is not one of {CAMERA_MODELS}")
    T = fwd.shape[0] + 1
    H, W = fwd.shape[1:3]
    thr = float(params.motion_threshold_px)
    out = np.zeros((T, H, W), bool)
    if T < 2:
        return out, []
    cams = [fit_camera_motion(fwd[t], model) for t in range(T - 1)]
    res_next = [_camera_residual(fwd[t], cams[t]) for t in range(T - 1)]  # frame t -> t+1
    res_prev = [_camera_residual(bwd[t], fit_camera_motion(bwd[t], model)) for t in range(T - 1)]  # t+1 -> t
    for t in range(T):
        rs = []
        if t < T - 1:
            rs.append(res_next[t])
        if t > 0:
            rs.append(res_prev[t - 1])
        moving = np.minimum.reduce(rs) > thr
        out[t] = clean_mask(moving, float(params.motion_min_area), int(params.motion_dilate_px))
    return out, cams


def static_tracks(xy: np.ndarray, visible: np.ndarray, cams: list[CameraMotion], threshold: float) -> np.ndarray:
    """(P,) bool: tracks whose RMS motion beyond the camera's is below `threshold` px/frame.

    xy are image coordinates (+0.5 convention) over the frames the cameras were
    fitted on (in temporal order). Tracks with no visible step are not static.
    """
    P, T = visible.shape
    if P == 0 or T < 2:
        return np.zeros(P, bool)
    sq = np.zeros(P)
    n = np.zeros(P)
    for t in range(T - 1):
        step = visible[:, t] & visible[:, t + 1]
        if step.any():
            r = cams[t].residual(xy[step, t] - 0.5, xy[step, t + 1] - 0.5)
            sq[step] += r**2
            n[step] += 1
    return (n > 0) & (np.sqrt(sq / np.maximum(n, 1)) < threshold)


def background_colour_mask(images: np.ndarray, background: Any, tol: float = 8.0) -> np.ndarray:
    """Pixels farther than `tol` (0..255) from the background colour."""
    bg = np.asarray(background, np.float32).reshape(-1)
    if bg.size == 1:
        bg = np.repeat(bg, 3)
    if bg.max() <= 1.0:
        bg = bg * 255.0
    diff = np.abs(images.astype(np.float32) - bg[:3]).max(axis=-1)
    return diff > tol
