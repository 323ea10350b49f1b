"""Rule forecast: thin wrapper around mogaf.stages.forecast_merge."""

from mogaf.stages import forecast_merge, run_stage

run_stage(
    forecast_merge,
    snakemake.log[0],
    model=snakemake.input.model,
    groups=snakemake.input.groups,
    split=snakemake.input.split,
    parts=list(snakemake.input.parts),
    out=snakemake.output[0],
    params=snakemake.params.forecast,
    method=snakemake.wildcards.method,
    seed=snakemake.params.seed,
)
