"""Stage export (-> export/{method}/index.json and export/{method}/ply/):
one method's forecast as PLY files in the original 3DGS layout, for
Gaussian-splatting viewers (SuperSplat, nerfstudio / gsplat tools, web viewers).

Opt-in: no other stage reads it and `make demo` does not build it. It reads
the model the forecasts start from (refined.h5, or recon.h5 without
refinement), forecast/{method}.h5, the split and scene.h5's evaluation
cameras, and writes
  ply/observed_t{step}.ply  the model at the last observed time step
  ply/forecast_t{step}.ply  the forecast at each chosen forecast step (export.steps)
  index.json                per file: kind, time step, normalised time, and the
                            evaluation cameras at that step (frame, K, w2c,
                            width, height); the SH degree, whether colours
                            are exact, the background colour, the counts.
Each file holds exactly the Gaussians the evaluation renders at its step:
the dynamic ones at that step's poses, then the static background.

Modules: params (ExportSettings), colors (the model's colours in 3DGS's SH
convention), ply (the PLY layout: SplatCloud, write_splat_ply,
read_splat_ply), clouds (a Model4D as splats, their render), stage
(run_export_stage).
"""

from .params import DEFAULT_PARAMS, EXPORT_STAGE, PLY_FOLDER, ply_folder

__all__ = ["DEFAULT_PARAMS", "EXPORT_STAGE", "PLY_FOLDER", "ply_folder"]
