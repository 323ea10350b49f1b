"""Rule recon: thin wrapper around mogaf.stages.recon."""

from mogaf.stages import recon, run_stage

run_stage(
    recon,
    snakemake.log[0],
    threads=snakemake.threads,
    scene=snakemake.input.scene,
    split=snakemake.input.split,
    priors=snakemake.input.priors,
    out=snakemake.output[0],
    params=snakemake.params.recon,
    seed=snakemake.params.seed,
    device=snakemake.params.device,
    checkpoint=snakemake.params.checkpoint,
)
