"""Rule group: thin wrapper around mogaf.stages.group."""

from mogaf.stages import group, run_stage

run_stage(
    group,
    snakemake.log[0],
    threads=snakemake.threads,
    model=snakemake.input.model,
    priors=snakemake.input.priors,
    scene=snakemake.input.scene,
    out=snakemake.output[0],
    params=snakemake.params.grouping,
    seed=snakemake.params.seed,
)
