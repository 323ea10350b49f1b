"""Rule export: thin wrapper around mogaf.stages.export."""

from mogaf.stages import export, run_stage

run_stage(
    export,
    snakemake.log[0],
    threads=snakemake.threads,
    model=snakemake.input.model,
    forecast=snakemake.input.forecast,
    scene=snakemake.input.scene,
    split=snakemake.input.split,
    out=snakemake.output.index,
    ply_dir=snakemake.output.ply,
    params=snakemake.params.export,
)
