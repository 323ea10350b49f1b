"""Parameters of the reconstruction stage (Shape-of-Motion style 4D Gaussians).

Every key has a default in DEFAULT_PARAMS. Values come from the official
Shape-of-Motion (SoM) implementation (vye16/shape-of-motion, flow3d/configs.py,
run_training.py, trainer.py, init_utils.py) where it has one; the comments
mark "SoM" for those and "CPU" where this package uses a smaller value so a
run fits a CPU budget (SoM trains on a GPU for ~25k steps of 8 frames with
40k fg + 100k bg Gaussians; the default synthetic scene here must finish in
about 4 minutes on 2 cores).

Knobs that trade quality for time: iterations, max_gaussians, num_fg_init,
num_bg_init, downscale, num_bases, batch_size, track_targets.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from ..errors import MogafError, refuse_unknown_params

DEFAULT_PARAMS: dict[str, Any] = {
    # ---- budget (quality vs time)
    "iterations": 1500,  # CPU (SoM: 500 epochs, ~25k steps of 8 frames)
    "iterations_scale": 1.0,  # multiplies `iterations` (error-against-run-time sweeps)
    "batch_size": 1,  # frames per step; CPU (SoM: 8)
    "downscale": 1,  # integer image downscale applied at training time
    "coarse_downscale": 2,  # coarse-to-fine: initialise and run the first part of training at 1/this resolution
    "coarse_fraction": 0.5,  # ... for this share of the iterations (0 = off)
    "max_gaussians": 30000,  # cap on fg + bg after densification; CPU (SoM: uncapped)
    "num_fg_init": 6000,  # CPU (SoM: num_fg 40000)
    "num_bg_init": 6000,  # CPU (SoM: num_bg 100000)
    "num_bases": 10,  # SoM num_motion_bases
    "sh_degree": 0,  # SoM uses plain RGB colours (degree 0)
    "background_gaussians": "auto",  # "auto" (monocular/iphone: yes, dnerf: no), "yes", "no"
    "content_threshold": 0.03,  # no background model: pixels this far from the background colour count as
    # foreground too (shadows, anti-aliased edges); 0 = use the priors' masks as they are
    # ---- initialisation
    "canonical_frame": -1,  # index among the observed frames; -1 = automatic (see mogaf.recon.init)
    "canonical_candidates": 3,  # no tracks/depth: best-scored frames tried with a short silhouette fit
    "init_min_cluster_fraction": 0.01,  # drop k-means clusters smaller than this share of tracks (SoM: 100 tracks)
    "init_coef_scale": 10.0,  # SoM: logits = 10 * exp(-d); d here in units of init_coef_length * fg extent
    "init_coef_length": 0.1,  # CPU/units: SoM uses metres directly
    "init_opacity": 0.7,  # SoM
    "init_optim_iters": 300,  # SoM run_initial_optim: 1000 (track-only fit, no rendering)
    "init_fg_dense_fraction": 0.5,  # share of fg Gaussians lifted from canonical-frame fg pixels (rest: tracks)
    "carve_window": 6,  # multi-view without depth: frames either side of the canonical time used to carve
    "carve_min_fraction": 0.75,  # a candidate point must fall in the (dilated) fg mask in this share of them
    "carve_dilate": 3,  # pixels of mask dilation for carving
    "carve_candidates": 400000,  # uniform candidates sampled in the volume
    # ---- learning rates (SoM configs.py)
    "lr_means": 1.6e-4,
    "lr_opacities_fg": 1e-2,
    "lr_opacities_bg": 5e-2,
    "lr_scales": 5e-3,  # decays x0.1 exponentially over training (SoM)
    "lr_quats": 1e-3,
    "lr_colors": 1e-2,
    "lr_motion_coefs": 1e-2,
    "lr_rots": 1.6e-4,
    "lr_transls": 1.6e-4,
    "lr_scene_scaled": True,  # means / translation LRs multiplied by scene extent (SoM scenes are ~unit scale)
    "lr_boost": 4.0,  # CPU: all LRs x this (far fewer steps than SoM); scales get it too
    # ---- losses (SoM LossesConfig)
    "w_rgb": 1.0,
    "ssim_weight": 0.2,  # rgb = 0.8 L1 + 0.2 (1 - SSIM)
    "w_mask": 1.0,
    "w_depth": 0.5,  # SoM w_depth_reg (disparity L1, 0.98 quantile)
    "w_depth_grad": 1.0,  # SoM w_depth_grad
    "w_track": 2.0,  # SoM w_track
    "w_smooth_bases": 10.0,  # SoM: 0.1. CPU: ~1.5k single-frame steps instead of ~25k x 8 frames; measured
    # (MuJoCo scene7 held-out 21.4 -> 24.2 dB, synthetic trajectory error 6.3 -> 4.5 cm, scene3 unchanged)
    "w_smooth_tracks": 2.0,  # SoM w_smooth_tracks
    "w_z_accel": 1.0,  # SoM w_z_accel
    "w_scale_var": 0.01,  # SoM w_scale_var
    "silhouette": "auto",  # "auto" (on when bases start at identity: no tracks + depth), "on", "off"
    "w_silhouette": 1.0,  # not in SoM: 2D distance-transform / coverage pull of projected fg centres (see trainer)
    "silhouette_pixels": 256,  # mask pixels per instance and frame for the coverage term
    "silhouette_decay": 0.9,  # the weight falls linearly by this fraction over training
    "lr_motion_identity_boost": 10.0,  # motion LRs x this when the bases start at identity (no track / silhouette fit)
    "silhouette_fit_iters": 400,  # no tracks/depth: fit bases to the masks before photometric training (0 = off)
    "silhouette_fit_points": 1500,  # fg centres used by that fit
    "silhouette_fit_frames": 16,  # frames per iteration of that fit
    "silhouette_fit_smooth": 0.05,  # weight of the basis smoothness (acceleration) in that fit
    "silhouette_fit_still": 0.05,  # weight of a velocity penalty in that fit (objects stay put unless the masks move)
    "hull_min_fraction": 0.8,  # after that fit: keep points inside the (dilated) masks of this share of frames
    "track_targets": 2,  # target frames per source frame for the 2D track loss; CPU (SoM: 4)
    "loss_quantile": 0.98,  # SoM: robust trimming of mask / depth / track losses
    "gap_interpolation": False,  # True: steps without a training frame = cubic spline through those with one
    # (False: left to the smoothness prior; measured better on MuJoCo scene7, noisy knots make splines overshoot)
    # ---- temporal curriculum (multi-view scenes without depth / tracks)
    "curriculum": "auto",  # "auto" (on when bases start at identity), "on", "off"
    "curriculum_fraction": 0.5,  # share of iterations over which the time window grows to all frames
    "curriculum_start": 3,  # initial half-window, in observed time steps
    # ---- adaptive density control (SoM OptimizerConfig), in iterations
    "warmup_steps": 100,  # SoM 200
    "control_every": 100,  # SoM
    "reset_opacity_every": 0,  # 0 = never; CPU (SoM: every 30 controls = 3000 steps, after our run ends)
    "stop_control_fraction": 0.8,  # SoM stops at 4000 / 5000 steps
    "densify_grad_threshold": 0.0002,  # SoM densify_xys_grad_threshold (NDC units)
    "densify_scale_threshold": 0.01,  # SoM, x scene extent
    "densify_screen_threshold": 0.05,  # SoM
    "cull_opacity_threshold": 0.1,  # SoM
    "cull_scale_threshold": 0.5,  # SoM, x scene extent
    "cull_screen_threshold": 0.15,  # SoM
    # ---- bookkeeping
    "log_every": 25,
    "checkpoint_every": 200,
    "eval_every": 100,  # training-curve PSNR on one fixed observed frame
    "backend": "auto",  # rasterizer backend (mogaf.render)
    "device": "auto",  # "auto" (cuda if available), "cpu", "cuda" (gsplat backend)
    "threads": 1,  # torch (and CPU rasterizer) threads during the stage; 0 = leave as set by the caller.
    # 1 keeps float reductions in one order (bitwise-reproducible artefacts) and avoids OpenMP
    # spin-waiting when the cores are shared; the per-step work is small, so little is lost.
}

CHOICES = {
    "device": ("auto", "cpu", "cuda"),
    "background_gaussians": ("auto", "yes", "no"),
    "curriculum": ("auto", "on", "off"),
    "silhouette": ("auto", "on", "off"),
}
INT_KEYS = {
    "iterations", "coarse_downscale", "canonical_frame", "canonical_candidates", "batch_size", "downscale", "max_gaussians", "num_fg_init", "num_bg_init", "num_bases",
    "sh_degree", "threads", "init_optim_iters", "carve_window", "carve_dilate", "carve_candidates", "track_targets",
    "curriculum_start", "warmup_steps", "control_every", "reset_opacity_every", "log_every", "checkpoint_every",
    "eval_every", "silhouette_pixels", "silhouette_fit_iters", "silhouette_fit_points", "silhouette_fit_frames",
}


def resolve_params(params: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Defaults <- params, type-checked; unknown keys are refused."""
    params = dict(params or {})
    refuse_unknown_params("recon", params, DEFAULT_PARAMS)
    out = dict(DEFAULT_PARAMS)
    out.update(params)
    for key, default in DEFAULT_PARAMS.items():
        value = out[key]
        if key in CHOICES:
            if value not in CHOICES[key]:
                raise MogafError(f"recon param '{key}' must be one of {', '.join(CHOICES[key])}, got {value!r}")
        elif isinstance(default, bool):
            if not isinstance(value, bool):
                raise MogafError(f"recon param '{key}' must be true or false, got {value!r}")
        elif key in INT_KEYS:
            if isinstance(value, bool) or not isinstance(value, (int, float)) or int(value) != value:
                raise MogafError(f"recon param '{key}' must be an integer, got {value!r}")
            out[key] = int(value)
            if out[key] < (-1 if key == "canonical_frame" else 0):
                raise MogafError(f"recon param '{key}' must be non-negative, got {value!r}")
        elif isinstance(default, float):
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise MogafError(f"recon param '{key}' must be a number, got {value!r}")
            out[key] = float(value)
    for key in ("iterations", "batch_size", "downscale", "coarse_downscale", "num_bases", "max_gaussians", "num_fg_init", "control_every",
                "log_every", "checkpoint_every", "eval_every"):
        if out[key] < 1:
            raise MogafError(f"recon param '{key}' must be at least 1, got {out[key]}")
    if out["iterations_scale"] <= 0:
        raise MogafError(f"recon param 'iterations_scale' must be positive, got {out['iterations_scale']}")
    out["iterations"] = max(1, int(round(out["iterations"] * out["iterations_scale"])))
    out["iterations_scale"] = 1.0  # applied (keeps the digest of equivalent settings equal)
    if out["sh_degree"] > 3:
        raise MogafError(f"recon param 'sh_degree' must be 0..3, got {out['sh_degree']}")
    return out
