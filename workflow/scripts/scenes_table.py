"""Rule scenes: thin wrapper around mogaf.stages.scenes_table."""

from mogaf.stages import run_stage, scenes_table

run_stage(scenes_table, snakemake.log[0], metrics_files=list(snakemake.input), out_md=snakemake.output[0])
