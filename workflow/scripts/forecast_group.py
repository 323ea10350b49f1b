"""Rule forecast_group: thin wrapper around mogaf.stages.forecast_group."""

from mogaf.stages import forecast_group, run_stage

run_stage(
    forecast_group,
    snakemake.log[0],
    threads=snakemake.threads,
    model=snakemake.input.model,
    groups=snakemake.input.groups,
    split=snakemake.input.split,
    out=snakemake.output[0],
    params=snakemake.params.forecast,
    method=snakemake.wildcards.method,
    group=snakemake.wildcards.group,
    seed=snakemake.params.seed,
    device=snakemake.params.device,
)
