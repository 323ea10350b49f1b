"""Reconstruction stage: observed frames + priors -> 4D Gaussians (recon.h5).

Shape-of-Motion-style dynamic Gaussians (canonical Gaussians moved by a
softmax blend of B SE(3) motion bases per observed time step) plus static
background Gaussians; see mogaf.representation for the stored schema,
mogaf.recon.params for the parameters and their sources.

Entry points (import them from their modules):
  stage.run_recon_stage(scene_h5, split_h5, priors_h5, out_h5, params, *, seed, checkpoint=None, progress=True)
  mogaf.rendering.render_model(model, timestep, K, w2c, width, height, features="rgb")
  mogaf.rendering.render_poses(model, means, quats, K, w2c, width, height, features="rgb")
"""

from .params import DEFAULT_PARAMS, resolve_params

__all__ = ["DEFAULT_PARAMS", "resolve_params"]
