"""Rule priors: thin wrapper around mogaf.stages.priors."""

from mogaf.stages import priors, run_stage

run_stage(
    priors,
    snakemake.log[0],
    scene=snakemake.input.scene,
    split=snakemake.input.split,
    out=snakemake.output[0],
    params=snakemake.params.priors,
    seed=snakemake.params.seed,
)
