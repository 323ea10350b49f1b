"""Motion-aware Gaussian grouping (paper Sec. 4.1) and the Gaga-4D baseline.

Modules
- params:    DEFAULT_PARAMS (paper values, Gaga defaults, own choices), resolve_params,
             RIGID_INIT_DEFAULTS.
- core:      MaskFrames, Groups, front-Gaussian seeding (mask_gaussians), has_rigid_groups.
- ours:      supplementary Algorithm 3 (seeding, feature-space region growing).
- gaga4d:    supplementary Algorithm 2 (projection-overlap memory bank, theta_ov).
- voting:    KNN voting for unassigned Gaussians.
- rigidity:  tau_k (label / config / estimated) and static flags.
- metrics:   grouping_quality: per-object IoU and ARI at held-out views.
- quality:   run_grouping_quality_stage -> grouping_quality.h5, read_grouping_quality.
- api:       group_gaussians (both methods, flags, compaction).
- stage:     run_group_stage -> groups.h5, run_rigid_init_stage -> rigid.h5,
             load_groups, read_rigid_init.
"""

from .params import DEFAULT_PARAMS, METHODS, RIGID_INIT_DEFAULTS, resolve_params

__all__ = ["DEFAULT_PARAMS", "METHODS", "RIGID_INIT_DEFAULTS", "resolve_params"]
