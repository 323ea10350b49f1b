"""Rule reconstruction_quality: thin wrapper around mogaf.stages.reconstruction_quality."""

from mogaf.stages import reconstruction_quality, run_stage

run_stage(
    reconstruction_quality,
    snakemake.log[0],
    threads=snakemake.threads,
    model=snakemake.input.model,
    scene=snakemake.input.scene,
    split=snakemake.input.split,
    out=snakemake.output[0],
    params=snakemake.params.reconstruction_quality,
)
