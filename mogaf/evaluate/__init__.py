"""Evaluation stage: render forecasts at the evaluation views and measure them.

For each enabled method it renders the forecast poses of the dynamic
Gaussians plus the static background at every evaluation view (held-out
cameras at forecast times), writes PNGs and a GT | forecast | error video,
and computes
- image metrics: PSNR, SSIM (11-px Gaussian window, sigma 1.5), LPIPS (AlexNet);
  for the iPhone protocol also mPSNR, mSSIM, mLPIPS with the covisibility
  masks when the dataset has them (DyCheck's protocol);
- tracking metrics where ground-truth tracks exist (synthetic scenes): GT
  surface points are attached to their nearest Gaussians at the last
  observed step (in each Gaussian's local frame) and carried by the
  forecast poses; 3D EPE, delta_3D, and on the train camera 2D AJ,
  delta_avg and occlusion accuracy (visibility from the rendered depth).
metrics.json also carries the model's quality at held-out views at observed
times (copied from reconstruction_quality/{refined,recon}.h5,
mogaf.reconstruction_quality),
the grouping quality (copied from grouping_quality.h5,
mogaf.grouping.quality), and the wall time and peak memory of
every stage that produced each method's result (Snakemake benchmark files).

Modules: params (DEFAULT_PARAMS), inputs (forecasts, benchmark files),
images (renders, PNGs, videos), tracking (tracking metrics), stage
(run_evaluate_stage).
"""

from .params import DEFAULT_PARAMS

__all__ = ["DEFAULT_PARAMS"]
