"""The forecast split: made once, here; every later stage reads only its frames.

Protocols
- iphone (DyCheck layout, incl. the synthetic scene): T time steps; observed
  = train-camera frames with t < r*T; evaluation = held-out (val) frames with
  t >= r*T; held-out frames with t < r*T measure reconstruction quality.
- dnerf (GaussianPrediction's protocol): frames of transforms_train with
  time < r are observed; frames of transforms_train and transforms_test with
  time >= r are forecast targets; test frames with time < r measure
  reconstruction quality. Validation frames are not used.

split.h5 holds frame ids (rows of scene.h5) per role and the time steps:
observed_timesteps = 0 .. T_obs-1 (the grid steps before the cut) and
forecast_timesteps = T_obs .. T-1.

Modules: params (check_ratio), core (Split, split.h5), protocol
(make_split), stage (split_scene), frames (reading a role's frames and
ground truth).
"""

from .core import ROLES, SPLIT_STAGE, Split, read_split, write_split
from .frames import (
    GROUND_TRUTH_TIME_AXES,
    evenly_spaced_frame_ids,
    load_evenly_spaced_frames,
    load_frames,
    load_ground_truth,
)
from .params import check_ratio
from .protocol import MIN_OBSERVED_TIMESTEPS, make_split
from .stage import split_scene

__all__ = [
    "GROUND_TRUTH_TIME_AXES",
    "MIN_OBSERVED_TIMESTEPS",
    "ROLES",
    "SPLIT_STAGE",
    "Split",
    "check_ratio",
    "evenly_spaced_frame_ids",
    "load_evenly_spaced_frames",
    "load_frames",
    "load_ground_truth",
    "make_split",
    "read_split",
    "split_scene",
    "write_split",
]
