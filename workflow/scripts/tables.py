"""Rule tables: thin wrapper around mogaf.stages.tables."""

from mogaf.stages import run_stage, tables

run_stage(
    tables,
    snakemake.log[0],
    metrics_files=list(snakemake.input) + list(snakemake.params.other_metrics),
    out_files=list(snakemake.output),
    params=snakemake.params.report,
    ablations=snakemake.params.ablations,
)
