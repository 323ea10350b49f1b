"""Rule split: thin wrapper around mogaf.stages.split."""

from mogaf.stages import run_stage, split

run_stage(
    split, snakemake.log[0], scene=snakemake.input.scene, out=snakemake.output[0], ratio=snakemake.wildcards.ratio
)
