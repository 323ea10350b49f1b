"""Shared pieces of the reconstruction initialisation (mogaf.recon.init).

The result type (InitResult), pixel/world geometry (unproject, project,
nearest-pixel sampling), the initial Gaussian attributes (knn_scale for the
sizes, random rotations, colour and coefficient logits, gaussian_tensors),
instance labels of pixels, the volume box of a scene and the background
samplers used by both initialisations (with tracks: init_tracks; without:
init_masks).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from ..camera import camera_centers
from .data import TrainData
from .model import num_sh_rest
from .params import load_settings


@dataclass
class InitResult:
    fg: dict[str, torch.Tensor]
    rot6d: torch.Tensor  # (B, T, 6)
    transl: torch.Tensor  # (B, T, 3)
    bg: dict[str, torch.Tensor] | None
    scene_scale: float
    canonical_frame: int
    motion_source: str  # "procrustes" (3D tracks), "silhouette" (fit to masks) or "identity"
    info: dict[str, Any] = field(default_factory=dict)


IDENTITY_6D = torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0])


def unproject(uv: np.ndarray, depth: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> np.ndarray:
    """Pixels (M,2) (+0.5 convention) with z-depth (M,) to world points (M,3)."""
    Kinv = np.linalg.inv(K)
    rays = np.concatenate([uv, np.ones((uv.shape[0], 1))], axis=1) @ Kinv.T
    cam = rays * depth[:, None]
    R, t = w2c[:3, :3], w2c[:3, 3]
    return (cam - t) @ R  # R^T (cam - t)


def project(points: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    cam = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[:, 2]
    uvw = cam @ K.T
    uv = uvw[:, :2] / np.where(np.abs(z) < 1e-9, 1e-9, z)[:, None]
    return uv, z


def knn_scale(points: np.ndarray, k: int = 3, clamp: bool = True) -> np.ndarray:
    """Mean distance to the k nearest neighbours (SoM's initial Gaussian size)."""
    from sklearn.neighbors import NearestNeighbors

    n = points.shape[0]
    if n <= 1:
        return np.full(n, 0.01, np.float64)
    kk = min(k, n - 1)
    nn = NearestNeighbors(n_neighbors=kk + 1).fit(points)
    d, _ = nn.kneighbors(points)
    s = d[:, 1:].mean(axis=1)
    s = np.maximum(s, 1e-6)
    if clamp and n > 20:
        s = np.clip(s, np.quantile(s, 0.05), np.quantile(s, 0.95))
    return s


def sample_pixels(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Nearest-pixel values of (H, W, ...) at continuous coordinates uv (M,2)."""
    H, W = img.shape[:2]
    c = np.clip(np.floor(uv[:, 0]).astype(np.int64), 0, W - 1)
    r = np.clip(np.floor(uv[:, 1]).astype(np.int64), 0, H - 1)
    return img[r, c]


def random_quats(n: int, rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True).clip(1e-12)
    return np.where(q[:, :1] < 0, -q, q)


def color_logits(rgb: np.ndarray) -> np.ndarray:
    c = np.clip(rgb, 0.02, 0.98)
    return np.log(c / (1 - c))


def logit(p: float) -> float:
    return float(np.log(p / (1 - p)))


def robust_extent(points: np.ndarray) -> float:
    """Half of the largest 5-95% quantile range over the axes (SoM's scene scale)."""
    if points.shape[0] < 2:
        return 1.0
    lo, hi = np.quantile(points, 0.05, axis=0), np.quantile(points, 0.95, axis=0)
    e = float(np.max(hi - lo) / 2.0)
    return e if e > 1e-6 else 1.0


def coef_logits_from_centres(points: np.ndarray, centres: np.ndarray, scale: float, length: float) -> np.ndarray:
    d = np.linalg.norm(points[:, None] - centres[None], axis=-1)
    return (scale * np.exp(-d / max(length, 1e-9))).astype(np.float32)


def gaussian_tensors(
    means: np.ndarray,
    colors: np.ndarray,
    rng: np.random.Generator,
    opacity: float,
    sh_degree: int,
    clamp_scale: bool,
    coef_logits: np.ndarray | None = None,
) -> dict[str, torch.Tensor]:
    n = means.shape[0]
    scales = knn_scale(means, 3, clamp=clamp_scale)
    out = {
        "means": torch.tensor(means, dtype=torch.float32),
        "quats": torch.tensor(random_quats(n, rng), dtype=torch.float32),
        "log_scales": torch.tensor(np.log(np.repeat(scales[:, None], 3, axis=1)), dtype=torch.float32),
        "opacity_logits": torch.full((n,), logit(opacity), dtype=torch.float32),
        "color_logits": torch.tensor(color_logits(colors), dtype=torch.float32),
    }
    if sh_degree > 0:
        out["sh_rest"] = torch.zeros((n, num_sh_rest(sh_degree), 3), dtype=torch.float32)
    if coef_logits is not None:
        out["motion_coef_logits"] = torch.tensor(coef_logits, dtype=torch.float32)
    return out


def pixel_labels(data: TrainData, f: int, rr: np.ndarray, cc: np.ndarray) -> np.ndarray:
    """Instance id of pixels (rows, cols) of frame f (1 for plain foreground when no instance masks)."""
    if data.instance_mask is not None:
        return data.instance_mask[f][rr, cc].astype(np.int64)
    return (data.fg_masks[f][rr, cc] > 0.5).astype(np.int64)


def _use_bg(params: dict, data: TrainData) -> bool:
    params = load_settings(params)
    mode = params.background_gaussians
    if mode == "auto":
        return data.layout == "iphone" and params.num_bg_init > 0
    return mode == "yes" and params.num_bg_init > 0


def _bg_from_depth(data: TrainData, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    F = data.num_frames
    pts, cols = [], []
    per = int(np.ceil(n / F))
    for f in range(F):
        m = (data.fg_masks[f] < 0.5) & data.depth_valid[f]
        rr, cc = np.nonzero(m)
        if rr.size == 0:
            continue
        sel = np.sort(rng.choice(rr.size, min(per, rr.size), replace=False))
        uv = np.stack([cc[sel] + 0.5, rr[sel] + 0.5], axis=1)
        pts.append(unproject(uv, data.depth[f][rr[sel], cc[sel]], data.K[f], data.w2c[f]))
        cols.append(data.images[f][rr[sel], cc[sel]])
    if not pts:
        return np.zeros((0, 3)), np.zeros((0, 3))
    P, C = np.concatenate(pts), np.concatenate(cols)
    if P.shape[0] > n:
        sel = np.sort(rng.choice(P.shape[0], n, replace=False))
        P, C = P[sel], C[sel]
    return P, C


def _volume_box(data: TrainData) -> tuple[np.ndarray, np.ndarray]:
    if data.point_cloud is not None and len(data.point_cloud) >= 8:
        p = np.asarray(data.point_cloud[:, :3], dtype=np.float64)
        lo, hi = p.min(0), p.max(0)
    else:
        c = camera_centers(data.w2c)
        lo, hi = c.min(0), c.max(0)
        pad = 0.05 * np.max(hi - lo) + 1e-3
        lo, hi = lo - pad, hi + pad
    return lo, hi


def _dilate(mask: np.ndarray, r: int) -> np.ndarray:
    if r <= 0:
        return mask
    import cv2

    k = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), k) > 0
