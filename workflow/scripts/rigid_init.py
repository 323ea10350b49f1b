"""Rule rigid_init: thin wrapper around mogaf.stages.rigid_init."""

from mogaf.stages import rigid_init, run_stage

run_stage(
    rigid_init,
    snakemake.log[0],
    model=snakemake.input.model,
    groups=snakemake.input.groups,
    out=snakemake.output[0],
    params=snakemake.params.rigid_init,
)
