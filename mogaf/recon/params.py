"""Parameters of the reconstruction stage (Shape-of-Motion style 4D Gaussians).

Every setting is a field of ReconSettings with its default and source
(DEFAULT_PARAMS is the same as a plain dict). Values come from the official
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
from dataclasses import dataclass
from typing import Any, Literal

from ..settings import check, defaults, load, setting


@dataclass(frozen=True)
class ReconSettings:
    """Settings of the reconstruction stage (config section `recon`)."""

    # ---- budget (quality vs time)
    iterations: int = setting(1500, "CPU (SoM: 500 epochs, ~25k steps of 8 frames)", minimum=1)
    iterations_scale: float = setting(
        1.0, "multiplies `iterations` (error-against-run-time sweeps)", exclusive_minimum=0
    )
    batch_size: int = setting(1, "frames per step; CPU (SoM: 8)", minimum=1)
    downscale: int = setting(1, "integer image downscale applied at training time", minimum=1)
    coarse_downscale: int = setting(
        2, "coarse-to-fine: initialise and run the first part of training at 1/this resolution", minimum=1
    )
    coarse_fraction: float = setting(0.5, "... for this share of the iterations (0 = off)")
    max_gaussians: int = setting(30000, "cap on fg + bg after densification; CPU (SoM: uncapped)", minimum=1)
    num_fg_init: int = setting(6000, "CPU (SoM: num_fg 40000)", minimum=1)
    num_bg_init: int = setting(6000, "CPU (SoM: num_bg 100000)", minimum=0)
    num_bases: int = setting(10, "SoM num_motion_bases", minimum=1)
    sh_degree: int = setting(0, "SoM uses plain RGB colours (degree 0)", minimum=0, maximum=3)
    background_gaussians: Literal["auto", "yes", "no"] = setting(
        "auto", '"auto" (monocular/iphone: yes, dnerf: no), "yes", "no"'
    )
    content_threshold: float = setting(
        0.03,
        "no background model: pixels this far from the background colour count as foreground too (shadows, anti-aliased edges); 0 = use the priors' masks as they are",
    )
    # ---- initialisation
    canonical_frame: int = setting(
        -1, "index among the observed frames; -1 = automatic (see mogaf.recon.init)", minimum=-1
    )
    canonical_candidates: int = setting(
        3, "no tracks/depth: best-scored frames tried with a short silhouette fit", minimum=0
    )
    init_min_cluster_fraction: float = setting(
        0.01, "drop k-means clusters smaller than this share of tracks (SoM: 100 tracks)"
    )
    init_coef_scale: float = setting(
        10.0, "SoM: logits = 10 * exp(-d); d here in units of init_coef_length * fg extent"
    )
    init_coef_length: float = setting(0.1, "CPU/units: SoM uses metres directly")
    init_opacity: float = setting(0.7, "SoM")
    init_optim_iters: int = setting(300, "SoM run_initial_optim: 1000 (track-only fit, no rendering)", minimum=0)
    init_fg_dense_fraction: float = setting(
        0.5, "share of fg Gaussians lifted from canonical-frame fg pixels (rest: tracks)"
    )
    carve_window: int = setting(
        6, "multi-view without depth: frames either side of the canonical time used to carve", minimum=0
    )
    carve_min_fraction: float = setting(
        0.75, "a candidate point must fall in the (dilated) fg mask in this share of them"
    )
    carve_dilate: int = setting(3, "pixels of mask dilation for carving", minimum=0)
    carve_candidates: int = setting(400000, "uniform candidates sampled in the volume", minimum=0)
    # ---- learning rates (SoM configs.py)
    lr_means: float = setting(1.6e-4, "learning rates (SoM configs.py)")
    lr_opacities_fg: float = setting(1e-2, "learning rates (SoM configs.py)")
    lr_opacities_bg: float = setting(5e-2, "learning rates (SoM configs.py)")
    lr_scales: float = setting(5e-3, "decays x0.1 exponentially over training (SoM)")
    lr_quats: float = setting(1e-3, "learning rates (SoM configs.py)")
    lr_colors: float = setting(1e-2, "learning rates (SoM configs.py)")
    lr_motion_coefs: float = setting(1e-2, "learning rates (SoM configs.py)")
    lr_rots: float = setting(1.6e-4, "learning rates (SoM configs.py)")
    lr_transls: float = setting(1.6e-4, "learning rates (SoM configs.py)")
    lr_scene_scaled: bool = setting(
        True, "means / translation LRs multiplied by scene extent (SoM scenes are ~unit scale)"
    )
    lr_boost: float = setting(4.0, "CPU: all LRs x this (far fewer steps than SoM); scales get it too")
    # ---- losses (SoM LossesConfig)
    w_rgb: float = setting(1.0, "losses (SoM LossesConfig)")
    ssim_weight: float = setting(0.2, "rgb = 0.8 L1 + 0.2 (1 - SSIM)")
    w_mask: float = setting(1.0, "losses (SoM LossesConfig)")
    w_depth: float = setting(0.5, "SoM w_depth_reg (disparity L1, 0.98 quantile)")
    w_depth_grad: float = setting(1.0, "SoM w_depth_grad")
    w_track: float = setting(
        2.0, "SoM w_track (SoM's w_depth_const term, the tracks' rendered depth against the depth prior, is not used)"
    )
    w_smooth_bases: float = setting(
        10.0,
        "weight of the motion bases' smoothness (acceleration) prior. CPU: stronger than SoM's 0.1, since a CPU run "
        "takes ~1.5k single-frame steps instead of SoM's ~25k steps of 8 frames",
    )
    smooth_bases: Literal["acceleration", "jerk"] = setting(
        "acceleration",
        '"acceleration" (SoM: second differences of the bases over time) or "jerk" (ours: third differences, so '
        "motion at constant acceleration, e.g. falling, is not slowed down towards both ends of the observation)",
    )
    w_smooth_tracks: float = setting(2.0, "SoM w_smooth_tracks")
    w_z_accel: float = setting(1.0, "SoM w_z_accel")
    w_speed: float = setting(
        0.0,
        "ours, not SoM's (0 = off): weight of the foreground Gaussians' mean speed between neighbouring steps (an L1 "
        "prior on motion, in scene scales per step): a Gaussian moves where the images ask it to and otherwise "
        "stays still, as a still body beside a moving part should without instance masks. Off by default: it also "
        "slows fast real motion, as the MuJoCo scenes' (docs/results.md)",
        minimum=0,
    )
    w_isometry: float = setting(
        0.0,
        "ours, not SoM's (0 = off): weight of the change, between neighbouring steps, of each foreground Gaussian's "
        "distance to its `isometry_neighbours` nearest canonical neighbours (an L1 prior on stretching, in scene "
        "scales per step): parts that the images move as one stay rigid, and unlike w_speed it never slows rigid motion",
        minimum=0,
    )
    isometry_neighbours: int = setting(8, "ours: neighbours per Gaussian for w_isometry", minimum=1)
    w_scale_var: float = setting(0.01, "SoM w_scale_var")
    silhouette: Literal["auto", "on", "off"] = setting(
        "auto", '"auto" (on when bases start at identity: no tracks + depth), "on", "off"'
    )
    w_silhouette: float = setting(
        1.0, "not in SoM: 2D distance-transform / coverage pull of projected fg centres (see trainer)"
    )
    silhouette_pixels: int = setting(256, "mask pixels per instance and frame for the coverage term", minimum=0)
    silhouette_decay: float = setting(0.9, "the weight falls linearly by this fraction over training")
    lr_motion_identity_boost: float = setting(
        10.0, "motion LRs x this when the bases start at identity (no track / silhouette fit)"
    )
    silhouette_fit_iters: int = setting(
        400, "no tracks/depth: fit bases to the masks before photometric training (0 = off)", minimum=0
    )
    silhouette_fit_points: int = setting(1500, "fg centres used by that fit", minimum=0)
    silhouette_fit_frames: int = setting(16, "frames per iteration of that fit", minimum=0)
    silhouette_fit_smooth: float = setting(0.05, "weight of the basis smoothness (acceleration) in that fit")
    silhouette_fit_still: float = setting(
        0.05, "weight of a velocity penalty in that fit (objects stay put unless the masks move)"
    )
    hull_min_fraction: float = setting(
        0.8, "after that fit: keep points inside the (dilated) masks of this share of frames"
    )
    track_targets: int = setting(2, "target frames per source frame for the 2D track loss; CPU (SoM: 4)", minimum=0)
    loss_quantile: float = setting(0.98, "SoM: robust trimming of mask / depth / track losses")
    gap_interpolation: bool = setting(
        False,
        "True: steps without a training frame = cubic spline through those with one; False: left to the smoothness "
        "prior (the default: splines through noisy knots overshoot)",
    )
    # ---- temporal curriculum (multi-view scenes without depth / tracks)
    curriculum: Literal["auto", "on", "off"] = setting("auto", '"auto" (on when bases start at identity), "on", "off"')
    curriculum_fraction: float = setting(0.5, "share of iterations over which the time window grows to all frames")
    curriculum_start: int = setting(3, "initial half-window, in observed time steps", minimum=0)
    # ---- adaptive density control (SoM OptimizerConfig), in iterations
    warmup_steps: int = setting(100, "SoM 200", minimum=0)
    control_every: int = setting(100, "SoM", minimum=1)
    reset_opacity_every: int = setting(
        0, "0 = never; CPU (SoM: every 30 controls = 3000 steps, after our run ends)", minimum=0
    )
    stop_control_fraction: float = setting(
        0.8, "ours: SoM stops at step 4000, of its 5000-step learning-rate schedule but of runs of 15-30k steps"
    )
    densify_grad_threshold: float = setting(0.0002, "SoM densify_xys_grad_threshold (NDC units)")
    densify_scale_threshold: float = setting(0.01, "SoM, x scene extent")
    densify_screen_threshold: float = setting(
        0.05,
        "SoM's value; SoM never updates the screen radii it compares (an out-of-place index_put), so it never acts there",
    )
    cull_opacity_threshold: float = setting(0.1, "SoM")
    cull_scale_threshold: float = setting(0.5, "SoM, x scene extent")
    cull_screen_threshold: float = setting(0.15, "SoM's value (inactive in SoM, as densify_screen_threshold)")
    # ---- bookkeeping
    log_every: int = setting(25, "bookkeeping", minimum=1)
    checkpoint_every: int = setting(200, "bookkeeping", minimum=1)
    eval_every: int = setting(100, "training-curve PSNR on one fixed observed frame", minimum=1)
    backend: Literal["auto", "cpu", "torch", "reference", "gsplat"] = setting(
        "auto", "rasterizer backend (mogaf.render)"
    )
    device: Literal["auto", "cpu", "cuda"] = setting(
        "auto", '"auto" (cuda if available), "cpu", "cuda" (gsplat backend)', injected=True
    )
    threads: int = setting(
        1,
        "torch (and CPU rasterizer) threads during the stage; 0 = leave as set by the caller. 1 keeps float reductions in one order (bitwise-reproducible artefacts) and avoids OpenMP spin-waiting when the cores are shared; the per-step work is small, so little is lost.",
        minimum=0,
    )


DEFAULT_PARAMS: dict[str, Any] = defaults(ReconSettings)


def load_settings(params: Mapping[str, Any] | ReconSettings | None) -> ReconSettings:
    """Resolved parameters (resolve_params' dict) as a frozen ReconSettings, what
    the stage's modules read; a ReconSettings is returned as it is."""
    return load(ReconSettings, "recon", params)


def resolve_params(params: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Defaults <- params, type-checked (ReconSettings); unknown keys are refused.
    `iterations_scale` is applied to `iterations` and then reset to 1, so
    equivalent settings share a digest."""
    out = check(ReconSettings, "recon", params)
    out["iterations"] = max(1, int(round(out["iterations"] * out["iterations_scale"])))
    out["iterations_scale"] = 1.0
    return out
