"""Rule runtime_report: thin wrapper around mogaf.stages.runtime_report."""

from mogaf.stages import run_stage, runtime_report

run_stage(
    runtime_report,
    snakemake.log[0],
    metrics_files=list(snakemake.input) + list(snakemake.params.other_metrics),
    out_csv=snakemake.output.csv,
    out_md=snakemake.output.md,
    out_png=snakemake.output.png,
    params=snakemake.params.report,
)
