"""Parameters of the grouping stages: group (DEFAULT_PARAMS, resolve_params) and
rigid_init (RIGID_INIT_DEFAULTS), grouping_quality (GroupingQualitySettings),
and _typed_params for parameters read back from an artefact's JSON attrs."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from ..settings import check, defaults, load, setting

METHODS = ("ours", "gaga4d")


# Values the paper gives are marked "paper"; values taken from Gaga's public
# implementation (weijielyu/Gaga, associate.py / mask/projector.py) are
# marked "Gaga"; the rest are this implementation's choices (documented in
# the docstrings of ours.py, gaga4d.py, voting.py, rigidity.py, metrics.py
# and api.py).
@dataclass(frozen=True)
class GroupingSettings:
    """Settings of the group stage (config section `grouping`)."""

    method: Literal["ours", "gaga4d"] = setting(
        "ours", '"ours" (supp. Algorithm 3) or "gaga4d" (supp. Algorithm 2 baseline)'
    )
    # --- ours: supp. "Motion-aware Gaussian Grouping" / "Iterative Region Growing"
    keyframe_stride: int = setting(
        5,
        "keyframes = every 5th observed frame in time order (the paper samples T_key keyframes, no value given)",
        minimum=1,
    )
    front_fraction: float = setting(
        0.4,
        'paper: "we extract the closest 40% front Gaussians with respect to the camera view"',
        exclusive_minimum=0,
        maximum=1,
    )
    front_patches: int = setting(
        32, "Gaga (num_patch=32): the front fraction is taken per cell of a 32x32 image grid", minimum=1
    )
    pca_scale: float = setting(
        0.3, 'paper: "scale the resulting PCA components by 0.3, and concatenate them with the Gaussian means"'
    )
    pca_components: int | None = setting(
        None, "None: the fewest components whose explained variance reaches pca_explained_variance"
    )
    pca_explained_variance: float = setting(
        0.95, "ours: supp. 'Motion-aware Gaussian Grouping' / 'Iterative Region Growing'"
    )
    grow_alpha: float = setting(
        1.0, 'eps_k = alpha * mean KNN distance in the group (paper: "the average neighbor distance")'
    )
    grow_knn: int = setting(8, 'K of KNN_K in eps_k (Algorithm 3, line "eps_k <- alpha * mean KNN_K(f_g)")', minimum=1)
    grow_radius_sample: int = setting(
        4096, "eps_k is averaged over at most this many members (distances are to all members)"
    )
    grow_max_iters: int = setting(100000, 'safety bound on "repeat until no group changes"')
    reseed_grown: bool = setting(
        False,
        "ours: True = at each keyframe the masks' front Gaussians win over earlier feature-space growth; False keeps "
        'the first assignment (Algorithm 3\'s "seed & merge" is a union, which leaves the conflict undecided). Off by '
        "default: it repairs growth leaking across object contacts but lowers the ARI on the synthetic scene",
    )
    grow_after_last_keyframe: bool = setting(
        True,
        "ours, not in the paper: True = one more growing pass after the last keyframe's seeding, so the Gaussians "
        "it seeds grow before the vote; Algorithm 3 votes right after that seeding (False, config/paper.yaml)",
    )
    mask_majority: bool = setting(
        False,
        "ours, not in the paper: True = after the last growing pass, a Gaussian that was among a mask's front "
        "Gaussians at some keyframes takes the identity most of them gave it (over half of its votes), so that "
        "neither one keyframe's seed nor growth across objects in contact decides it alone (variant mask_majority). "
        "Off by default: on the shared MuJoCo scenes it repairs groups that had taken most of another object, but "
        "the forecasts' means do not change (docs/results.md)",
    )
    vote_knn: int = setting(8, 'paper: "voting among the 8 nearest group-assigned neighbors"', minimum=1)
    vote_fraction: float = setting(
        0.5,
        'paper: "reassign only the closest 50% of unassigned Gaussians" (repeated rounds, see voting.py)',
        exclusive_minimum=0,
        maximum=1,
    )
    # --- gaga4d: supp. "Naive Extension of Static Gaussian Grouping"
    overlap_threshold: float = setting(
        0.1, "Gaga: associate.py --overlap_threshold default 0.1 (theta_ov)", exclusive_minimum=0, maximum=1
    )
    gaga_front_fraction: float = setting(
        0.2, "Gaga: associate.py --front_percentage default 0.2", exclusive_minimum=0, maximum=1
    )
    gaga_frame_stride: int = setting(1, "Algorithm 2 visits every observed frame (t = 1..T)", minimum=1)
    # --- rigidity (tau_k) and static groups
    rigid_override: dict = setting(
        {},
        '{instance name or id: 0/1}; source "config"; wins over labels and estimates',
        schema={"additionalProperties": {"anyOf": [{"type": "boolean"}, {"type": "integer", "enum": [0, 1]}]}},
    )
    rigidity_threshold: float = setting(
        0.05, "rigid iff RMS residual of the best per-time rigid fit / RMS group extent < this"
    )
    rigidity_max_points: int = setting(4096, "members used for the rigidity estimate (deterministic subsample)")
    static_threshold: float = setting(
        0.01, "a group is static if its members move less than this fraction of the scene extent"
    )
    static_quantile: float = setting(0.95, "... taken at this quantile of per-Gaussian displacement in the group")
    # A still body with one moving part (a chest and its lid) under one mask:
    # its still members become a static group of their own (rigidity.split_still_members).
    split_still_members: Literal["never", "unlabelled", "not_rigid"] = setting(
        "unlabelled",
        'not in the paper (its setting: never, config/paper.yaml): "unlabelled" splits groups whose mask carries '
        'no rigid flag (a foreground-only mask, no mask), "not_rigid" also those labelled non-rigid. On the scene '
        "family's scenes without masks it separates resting parts and objects the grouping had merged "
        "(docs/forecasting.md)",
    )
    split_neighbors: int = setting(16, "a member's motion is averaged over this many nearest members", minimum=1)
    split_motion_ratio: float = setting(
        3.0, "split only where the moving members' median motion is this many times the still ones'", minimum=1
    )
    split_min_fraction: float = setting(
        0.1,
        "split only where the still and the moving members are each at least this share of the group",
        exclusive_minimum=0,
        maximum=0.5,
    )
    seed: int = setting(0, injected=True)


DEFAULT_PARAMS: dict[str, Any] = defaults(GroupingSettings)


def resolve_params(params: dict[str, Any] | None) -> dict[str, Any]:
    """Defaults <- params, checked (GroupingSettings); unknown keys are refused."""
    return check(GroupingSettings, "grouping", params)


def load_settings(params: dict[str, Any] | GroupingSettings | None) -> GroupingSettings:
    """resolve_params as a frozen GroupingSettings (what the grouping's modules read)."""
    return load(GroupingSettings, "grouping", params)


@dataclass(frozen=True)
class RigidInitSettings:
    """Settings of the rigid_init stage (config section `rigid_init`)."""

    # The paper's alignment (supp. "Rigid Motion Initialization") is unweighted;
    # "opacity" weights every Gaussian by its opacity.
    weights: Literal["uniform", "opacity"] = setting("uniform", "'opacity' weights every Gaussian by its opacity.")
    time_chunk: int = setting(64, "observed steps solved at once (bounds memory for big groups)", minimum=1)


RIGID_INIT_DEFAULTS: dict[str, Any] = defaults(RigidInitSettings)


def _typed_params(raw: dict[str, Any]) -> dict[str, Any]:
    """Params read back from JSON attrs (floats are stored as text)."""
    out: dict[str, Any] = {}
    for key, value in raw.items():
        default = DEFAULT_PARAMS.get(key, RIGID_INIT_DEFAULTS.get(key))
        if isinstance(value, str) and not isinstance(default, str):
            try:
                number = float(value)
            except ValueError:
                out[key] = value
                continue
            out[key] = (
                int(number) if isinstance(default, (int, np.integer)) and not isinstance(default, bool) else number
            )
        else:
            out[key] = value
    return out


@dataclass(frozen=True)
class GroupingQualitySettings:
    """Settings of the grouping_quality stage (config section `grouping_quality`)."""

    alpha: float = setting(
        0.5, "a pixel is labelled where the rendered alpha exceeds this", exclusive_minimum=0, exclusive_maximum=1
    )
    pixels: Literal["foreground", "all"] = setting(
        "foreground", 'ARI over GT-foreground U predicted-foreground pixels ("all": every pixel)'
    )
    max_frames: int = setting(0, "held-out frames rendered (evenly spaced); 0 = all", minimum=0)
