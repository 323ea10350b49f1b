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
- `background_colour_mask`: for composited synthetic renders (D-NeRF without
  alpha), pixels that differ from the known background colour.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import cv2
import numpy as np

from ..errors import MogafError

CAMERA_MODELS = ("homography", "fundamental", "none")


def _camera_residual(flow: np.ndarray, model: str, stride: int = 4) -> np.ndarray:
    """Per-pixel residual (px) of `flow` after removing the camera motion."""
    H, W = flow.shape[:2]
    mag = np.linalg.norm(flow, axis=-1)
    if model == "none":
        return mag
    ys, xs = np.mgrid[0:H:stride, 0:W:stride]
    src = np.stack([xs.ravel(), ys.ravel()], -1).astype(np.float32)
    dst = src + flow[ys.ravel(), xs.ravel()]
    if len(src) < 8:
        return mag
    gy, gx = np.mgrid[0:H, 0:W].astype(np.float32)
    if model == "homography":
        Hm, inl = cv2.findHomography(src, dst, cv2.RANSAC, 1.0, maxIters=500, confidence=0.99)
        if Hm is None or inl is None or inl.mean() < 0.2:
            return mag
        pts = np.stack([gx, gy, np.ones_like(gx)], -1) @ Hm.T
        pred = pts[..., :2] / np.where(np.abs(pts[..., 2:]) < 1e-9, 1e-9, pts[..., 2:])
        return np.linalg.norm(np.stack([gx, gy], -1) + flow - pred, axis=-1)
    Fm, inl = cv2.findFundamentalMat(src, dst, cv2.FM_RANSAC, 1.0, 0.99)
    if Fm is None or Fm.shape != (3, 3) or inl is None or inl.mean() < 0.2:
        return mag
    x1 = np.stack([gx, gy, np.ones_like(gx)], -1)
    x2 = np.concatenate([x1[..., :2] + flow, np.ones_like(gx)[..., None]], -1)
    Fx1 = x1 @ Fm.T
    Ftx2 = x2 @ Fm
    num = np.abs(np.sum(x2 * Fx1, -1))
    den = np.sqrt(Fx1[..., 0] ** 2 + Fx1[..., 1] ** 2 + Ftx2[..., 0] ** 2 + Ftx2[..., 1] ** 2) + 1e-9
    return num / den


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


def motion_segmentation(fwd: np.ndarray, bwd: np.ndarray, params: Mapping[str, Any]) -> np.ndarray:
    """(T, H, W) bool moving-pixel masks from consecutive flows (T-1, H, W, 2)."""
    model = str(params["motion_camera_model"]).lower()
    if model not in CAMERA_MODELS:
        raise MogafError(f"priors: motion_camera_model {model!r} is not one of {CAMERA_MODELS}")
    T = fwd.shape[0] + 1
    H, W = fwd.shape[1:3]
    thr = float(params["motion_threshold_px"])
    out = np.zeros((T, H, W), bool)
    if T < 2:
        return out
    res_next = [_camera_residual(fwd[t], model) for t in range(T - 1)]  # frame t -> t+1
    res_prev = [_camera_residual(bwd[t], model) for t in range(T - 1)]  # frame t+1 -> t
    for t in range(T):
        rs = []
        if t < T - 1:
            rs.append(res_next[t])
        if t > 0:
            rs.append(res_prev[t - 1])
        moving = np.minimum.reduce(rs) > thr
        out[t] = clean_mask(moving, float(params["motion_min_area"]), int(params["motion_dilate_px"]))
    return out


def background_colour_mask(images: np.ndarray, background: Any, tol: float = 8.0) -> np.ndarray:
    """Pixels farther than `tol` (0..255) from the background colour."""
    bg = np.asarray(background, np.float32).reshape(-1)
    if bg.size == 1:
        bg = np.repeat(bg, 3)
    if bg.max() <= 1.0:
        bg = bg * 255.0
    diff = np.abs(images.astype(np.float32) - bg[:3]).max(axis=-1)
    return diff > tol
