"""Group-wise refinement (paper Sec. 4.2, supp. "Refinement of 4DGS Representation").

recon.h5 + groups.h5 (+ rigid.h5) -> refined.h5. Training continues from the
reconstruction with

    L_total = L_recon + sum_k [ tau_k lambda_rigid L_rigid^(k) + (1 - tau_k) lambda_nr L_nr^(k) ]

    L_rigid^(k) = sum_t sum_{g in G_k} || mu_{t,g} - (R^k_t mu_{c,g} + t^k_t) ||^2
    L_nr^(k)    = sum_{g in G_k} sum_{g' in NN(g)} || w_g - w_g' ||^2

where L_recon is the reconstruction stage's own loss (same weights, same
data), (R^k_t, t^k_t) start at the rigid_init Procrustes fits and are
optimised with the bases, and w are the softmax motion coefficients.

Choices where the paper is silent (each a parameter in REFINE_DEFAULTS):
  * Units: squared distances are divided by scene_scale^2 so lambda_rigid is
    scale free; the sum over t is estimated each step from `rigid_times`
    random observed steps (times T / rigid_times), the sum over g from at most
    `rigid_members` random members (times |G_k| / sample), so the loss is an
    unbiased estimate of the paper's sums divided by scene_scale^2 and T.
  * NN(g): the `nr_neighbors` nearest canonical-space members of the same
    group within a fixed radius of `nr_radius_factor` x the group's median
    nearest-neighbour distance, found once with a KD-tree.
  * No densification, splitting or pruning: the Gaussian set (and with it the
    group ids) stays the one grouped; static groups are left to L_recon.

A scene with no dynamic group (nothing moves) is a no-op: refined.h5 is the
reconstruction with the group ids added.

Modules: params (REFINE_DEFAULTS, resolve_params), trainer (RefineTrainer and
the neighbour pairs), stage (run_refine_stage).
"""

from .params import FIXED_RECON, REFINE_DEFAULTS, resolve_params

__all__ = ["FIXED_RECON", "REFINE_DEFAULTS", "resolve_params"]
