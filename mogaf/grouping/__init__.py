"""Motion-aware Gaussian grouping (paper Sec. 4.1) and the Gaga-4D baseline.

Modules
- params:    DEFAULT_PARAMS (paper values, Gaga defaults, own choices), resolve_params,
             RIGID_INIT_DEFAULTS.
- core:      MaskFrames, Groups, front-Gaussian seeding (mask_gaussians).
- ours:      supplementary Algorithm 3 (seeding, feature-space region growing).
- gaga4d:    supplementary Algorithm 2 (projection-overlap memory bank, theta_ov).
- voting:    KNN voting for unassigned Gaussians.
- rigidity:  tau_k (label / config / estimated) and static flags.
- metrics:   grouping_quality: per-object IoU and ARI at held-out views.
- quality:   run_grouping_quality_stage -> grouping_quality.h5, read_grouping_quality.
- api:       group_gaussians (both methods, flags, compaction).
- stage:     run_group_stage -> groups.h5, run_rigid_init_stage -> rigid.h5,
             has_rigid_groups, load_groups, read_rigid_init.
"""

from ..lazy import lazy_exports
from .params import DEFAULT_PARAMS, METHODS, RIGID_INIT_DEFAULTS, resolve_params

# Entry points load with their module on first use (mogaf.lazy): importing the
# package for its settings (params) stays light.
__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "group_gaussians": ".api",
        "instance_table": ".api",
        "Groups": ".core",
        "InstanceTable": ".core",
        "MaskFrames": ".core",
        "mask_gaussians": ".core",
        "adjusted_rand_index": ".metrics",
        "grouping_quality": ".metrics",
        "render_group_labels": ".metrics",
        "GROUP_STAGE": ".stage",
        "RIGID_STAGE": ".stage",
        "has_rigid_groups": ".stage",
        "load_groups": ".stage",
        "read_rigid_init": ".stage",
        "rigid_init": ".stage",
        "run_group_stage": ".stage",
        "run_rigid_init_stage": ".stage",
        "write_groups": ".stage",
    },
)

__all__ = [
    "DEFAULT_PARAMS",
    "GROUP_STAGE",
    "METHODS",
    "RIGID_INIT_DEFAULTS",
    "RIGID_STAGE",
    "Groups",
    "InstanceTable",
    "MaskFrames",
    "adjusted_rand_index",
    "group_gaussians",
    "grouping_quality",
    "has_rigid_groups",
    "instance_table",
    "load_groups",
    "mask_gaussians",
    "read_rigid_init",
    "render_group_labels",
    "resolve_params",
    "rigid_init",
    "run_group_stage",
    "run_rigid_init_stage",
    "write_groups",
]
