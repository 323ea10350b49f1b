"""Reconstruction stage: observed frames + priors -> 4D Gaussians (recon.h5).

Shape-of-Motion-style dynamic Gaussians (canonical Gaussians moved by a
softmax blend of B SE(3) motion bases per observed time step) plus static
background Gaussians; see mogaf.representation for the stored schema,
mogaf.recon.params for the parameters and their sources.

Entry points:
  run_recon_stage(scene_h5, split_h5, priors_h5, out_h5, params, *, seed, checkpoint=None, progress=True)
  render_model(model, timestep, K, w2c, width, height, features="rgb")
  render_poses(model, means, quats, K, w2c, width, height, features="rgb")
"""

from ..lazy import lazy_exports
from .params import DEFAULT_PARAMS, resolve_params

# Entry points load with their module on first use (mogaf.lazy): importing the
# package for its settings (params) stays light.
__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "render_model": "..rendering",
        "render_poses": "..rendering",
        "run_recon_stage": ".stage",
        "stage_digest": ".stage",
    },
)

__all__ = ["DEFAULT_PARAMS", "resolve_params", "render_model", "render_poses", "run_recon_stage", "stage_digest"]
