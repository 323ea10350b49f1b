"""Per-view image metrics as one dict, and their mean over views."""

from __future__ import annotations

import math

import numpy as np

from .image import mpsnr, mssim, psnr, ssim
from .lpips import lpips, mlpips


def image_metrics(
    pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None, masked: bool, use_lpips: bool
) -> dict[str, float]:
    """PSNR, SSIM (and LPIPS); with `masked` (DyCheck's iPhone protocol) also
    their co-visible versions, over `mask` or, without one, every pixel."""
    out = {"psnr": psnr(pred, gt), "ssim": ssim(pred, gt)}
    if use_lpips:
        out["lpips"] = lpips(pred, gt)
    if masked:
        m = np.ones(gt.shape[:2], np.float32) if mask is None else mask
        if m.sum() > 0:  # a view with no co-visible pixel has no masked metric
            out["mpsnr"] = mpsnr(pred, gt, m)
            out["mssim"] = mssim(pred, gt, m)
            if use_lpips:
                out["mlpips"] = mlpips(pred, gt, m)
    return {k: float(v) for k, v in out.items()}


def mean_metrics(per_view: list[dict[str, float]]) -> dict[str, float]:
    """Mean of each metric over the views that have it, finite values only
    (a perfect render's PSNR is +inf)."""
    keys = sorted({k for d in per_view for k in d})
    out = {}
    for k in keys:
        vals = [d[k] for d in per_view if k in d and math.isfinite(d[k])]
        if vals:
            out[k] = float(np.mean(vals))
    return out
