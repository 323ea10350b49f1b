"""Rule refine: thin wrapper around mogaf.stages.refine."""

from mogaf.stages import refine, run_stage

run_stage(
    refine,
    snakemake.log[0],
    threads=snakemake.threads,
    model=snakemake.input.model,
    groups=snakemake.input.groups,
    rigid=snakemake.input.get("rigid"),
    priors=snakemake.input.priors,
    scene=snakemake.input.scene,
    split=snakemake.input.split,
    out=snakemake.output[0],
    params=snakemake.params.refine,
    seed=snakemake.params.seed,
    device=snakemake.params.device,
    checkpoint=snakemake.params.checkpoint,
)
