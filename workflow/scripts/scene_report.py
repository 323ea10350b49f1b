"""Rule scene_report: thin wrapper around mogaf.stages.scene_report."""

from mogaf.stages import run_stage, scene_report

run_stage(
    scene_report,
    snakemake.log[0],
    renders=snakemake.input.renders,
    metrics=snakemake.input.metrics,
    grouping_quality=snakemake.input.grouping_quality,
    reconstruction_quality=snakemake.input.reconstruction_quality,
    out_videos=snakemake.output.videos,
    out_quality=snakemake.output.quality,
)
