"""Synthetic 2D motion for the tracker and the priors: textured squares
sliding (sub-pixel) over a static textured background, with an optional
occluder entering from the right."""

from __future__ import annotations

import cv2
import numpy as np


def texture(rng: np.random.Generator, h: int, w: int, sigma: float = 1.5) -> np.ndarray:
    """Smooth random colour texture in [0, 255] (float32)."""
    t = rng.uniform(0, 255, (h, w, 3)).astype(np.float32)
    t = cv2.GaussianBlur(t, (0, 0), sigma)
    t -= t.min(axis=(0, 1))
    t *= 255.0 / np.maximum(t.max(axis=(0, 1)), 1e-6)
    return t


def paste(canvas: np.ndarray, tex: np.ndarray, x: float, y: float) -> np.ndarray:
    """Composite `tex` with its top-left corner at sub-pixel (x, y); returns the alpha."""
    H, W = canvas.shape[:2]
    M = np.float32([[1, 0, x], [0, 1, y]])
    layer = cv2.warpAffine(tex, M, (W, H), flags=cv2.INTER_LINEAR)
    alpha = cv2.warpAffine(np.ones(tex.shape[:2], np.float32), M, (W, H), flags=cv2.INTER_LINEAR)[..., None]
    canvas[:] = canvas * (1 - alpha) + layer * alpha
    return alpha[..., 0]


def moving_squares(rng, T, H, W, squares, occluder=None):
    """Frames with textured squares [(x0, y0, vx, vy, size)] over a static textured background.

    Returns frames (T,H,W,3) uint8, per-square alpha (S,T,H,W) and occluder alpha (T,H,W).
    """
    bg = texture(rng, H, W, 2.0) * 0.6
    texs = [texture(rng, s, s, 1.2) for *_, s in squares]
    occ_tex = texture(rng, H, 30, 1.2) if occluder else None
    frames = np.zeros((T, H, W, 3), np.uint8)
    alphas = np.zeros((len(squares), T, H, W), np.float32)
    occ = np.zeros((T, H, W), np.float32)
    for t in range(T):
        c = bg.copy()
        for k, ((x0, y0, vx, vy, _), tex) in enumerate(zip(squares, texs)):
            alphas[k, t] = paste(c, tex, x0 + vx * t, y0 + vy * t)
        if occluder:
            ox0, ovx, t_in = occluder
            if t >= t_in:
                occ[t] = paste(c, occ_tex, ox0 + ovx * (t - t_in), 0.0)
        frames[t] = np.clip(np.rint(c), 0, 255).astype(np.uint8)
    return frames, alphas, occ
