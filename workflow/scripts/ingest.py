"""Rule ingest: thin wrapper around mogaf.stages.ingest."""

from mogaf.stages import ingest, run_stage

run_stage(
    ingest,
    snakemake.log[0],
    folder=snakemake.input[0],
    out=snakemake.output[0],
    layout=snakemake.params.layout,
    options=snakemake.params.options,
    dataset=snakemake.wildcards.dataset,
    scene=snakemake.wildcards.scene,
)
