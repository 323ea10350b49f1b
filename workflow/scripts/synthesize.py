"""Rule synthesize: thin wrapper around mogaf.stages.synthesize."""

from mogaf.stages import run_stage, synthesize

run_stage(
    synthesize,
    snakemake.log[0],
    out_dir=snakemake.output[0],
    params=snakemake.params.synthetic,
    job_threads=snakemake.threads,
)
