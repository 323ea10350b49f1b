"""Rule grouping_quality: thin wrapper around mogaf.stages.grouping_quality."""

from mogaf.stages import grouping_quality, run_stage

run_stage(
    grouping_quality,
    snakemake.log[0],
    threads=snakemake.threads,
    grouped_model=snakemake.input.grouped_model,
    groups=snakemake.input.groups,
    scene=snakemake.input.scene,
    split=snakemake.input.split,
    out=snakemake.output[0],
    params=snakemake.params.grouping_quality,
)
