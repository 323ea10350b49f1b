"""Stage reconstruction_quality (-> reconstruction_quality/{refined,recon}.h5):
the 4D model's image quality at held-out views at observed times.

Its own stage, not part of evaluation, so that the variants forecasting from
one model (e.g. every forecaster ablation) render these views once. It reads
the model the forecasts start from (refined.h5, or recon.h5 without
refinement), the split and scene.h5's "evaluation_observed" frames: held-out
cameras, observed times only, so no future frame is opened.

reconstruction_quality/{model}.h5 (stage "reconstruction_quality"):
  frame_ids (F,) int64     scene frames rendered (evenly spaced, at most max_frames)
  timesteps (F,) int64     their time steps
  camera_ids (F,) int64    their cameras (absent in an artefact written before it was recorded)
  per_frame/<metric> (F,)  float64: each metric every frame has, where finite in all
  attrs: params (JSON), heldout_observed (JSON: mean PSNR and SSIM, and for
    the iPhone protocol mPSNR and mSSIM over the co-visible pixels; a frame
    whose value is not finite, e.g. a perfect render, is left out of a mean),
    observed_motion (JSON, scenes with ground-truth surface points, else {}:
    the model's observed trajectories against them, measure.observed_motion:
    epe_3d, velocity_error, last_velocity_error and the points' speed, in
    scene units per step; still_points and still_jitter where some points
    never move)
metrics.json["reconstruction"] copies it: {"heldout_observed": ..., "num_frames": F,
"observed_motion": ...}, without the first two where the split has no
held-out view at an observed step, without the last without ground truth.

Modules: params (DEFAULT_PARAMS), measure (the metrics), stage (the
artefact).
"""

from .params import DEFAULT_PARAMS, RECONSTRUCTION_QUALITY_STAGE

__all__ = ["DEFAULT_PARAMS", "RECONSTRUCTION_QUALITY_STAGE"]
