"""Per-view image metrics as one dict, and their mean over views."""

from __future__ import annotations

import math

import numpy as np

from .image import mpsnr, mssim, psnr, ssim, ssim_padded
from .lpips import MIN_SIZE as LPIPS_MIN_SIZE
from .lpips import lpips, mlpips

SSIM_MIN_SIZE = 11  # DyCheck's SSIM window


def metrics_left_out(height: int, width: int, use_lpips: bool) -> dict[str, str]:
    """The metrics images of this size cannot have, each with the reason:
    `image_metrics` leaves them out (and their masked versions)."""
    side = min(height, width)
    out = {}
    if side < SSIM_MIN_SIZE:
        out["ssim"] = f"images are {width}x{height}, smaller than SSIM's {SSIM_MIN_SIZE}x{SSIM_MIN_SIZE} px window"
    if use_lpips and side < LPIPS_MIN_SIZE:
        out["lpips"] = (
            f"images are {width}x{height}, smaller than the {LPIPS_MIN_SIZE}x{LPIPS_MIN_SIZE} px LPIPS's AlexNet needs"
        )
    return out


def image_metrics(
    pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None, masked: bool, use_lpips: bool
) -> dict[str, float]:
    """PSNR, SSIM (and LPIPS); with `masked` (DyCheck's iPhone protocol) also
    their co-visible versions, over `mask` or, without one, every pixel.
    SSIM is DyCheck's under the iPhone protocol, GaussianPrediction's
    (`ssim_padded`) under the D-NeRF one. What images this small cannot have
    is left out (`metrics_left_out`)."""
    left_out = metrics_left_out(gt.shape[0], gt.shape[1], use_lpips)
    use_ssim = "ssim" not in left_out
    use_lpips = use_lpips and "lpips" not in left_out
    out = {"psnr": psnr(pred, gt)}
    if use_ssim:
        out["ssim"] = ssim(pred, gt) if masked else ssim_padded(pred, gt)
    if use_lpips:
        out["lpips"] = lpips(pred, gt)
    if masked:
        m = np.ones(gt.shape[:2], np.float32) if mask is None else mask
        if m.sum() > 0:  # a view with no co-visible pixel has no masked metric
            out["mpsnr"] = mpsnr(pred, gt, m)
            if use_ssim:
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
