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

from ..lazy import lazy_exports
from .params import DEFAULT_PARAMS, EXPORT_STAGE, PLY_FOLDER, ply_folder

# Entry points load with their module on first use (mogaf.lazy): importing the
# package for its settings (params) stays light.
__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "splat_colors": ".colors",
        "splat_sh": ".colors",
        "SplatCloud": ".ply",
        "read_splat_ply": ".ply",
        "splat_property_names": ".ply",
        "write_splat_ply": ".ply",
        "model_splats": ".clouds",
        "posed_splats": ".clouds",
        "render_splats": ".clouds",
        "run_export_stage": ".stage",
    },
)

__all__ = [
    "DEFAULT_PARAMS",
    "EXPORT_STAGE",
    "PLY_FOLDER",
    "SplatCloud",
    "model_splats",
    "ply_folder",
    "posed_splats",
    "read_splat_ply",
    "render_splats",
    "run_export_stage",
    "splat_colors",
    "splat_property_names",
    "splat_sh",
    "write_splat_ply",
]
