"""Evaluation metrics: image quality (PSNR, SSIM, LPIPS; plain and masked) and point tracking.

Each function documents its exact definition and its upstream source
(DyCheck for the masked image metrics, the LPIPS reference implementation,
Shape-of-Motion and TAP-Vid for tracking). torch is imported only when LPIPS
is used.
"""

from mogaf.metrics.image import gaussian_window, masked_mean, mpsnr, mssim, psnr, ssim, ssim_padded
from mogaf.metrics.lpips import (
    convert_lpips_sdist,
    get_lpips_model,
    load_lpips_weights,
    lpips,
    lpips_map,
    mlpips,
)
from mogaf.metrics.lpips_weights import default_weights_path, load_numpy_pickle
from mogaf.metrics.tracking import (
    average_jaccard,
    delta_3d,
    delta_avg,
    epe_3d,
    occlusion_accuracy,
    tracking_metrics,
)
from mogaf.metrics.views import image_metrics, mean_metrics, metrics_left_out

__all__ = [
    "masked_mean",
    "psnr",
    "mpsnr",
    "ssim",
    "mssim",
    "ssim_padded",
    "gaussian_window",
    "convert_lpips_sdist",
    "default_weights_path",
    "get_lpips_model",
    "load_lpips_weights",
    "load_numpy_pickle",
    "lpips",
    "lpips_map",
    "mlpips",
    "epe_3d",
    "delta_3d",
    "average_jaccard",
    "delta_avg",
    "occlusion_accuracy",
    "tracking_metrics",
    "image_metrics",
    "metrics_left_out",
    "mean_metrics",
]
