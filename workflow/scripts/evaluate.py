"""Rule evaluate: thin wrapper around mogaf.stages.evaluate."""

from mogaf.stages import evaluate, run_stage

inputs = dict(snakemake.input.items())
run_stage(
    evaluate,
    snakemake.log[0],
    threads=snakemake.threads,
    scene=inputs["scene"],
    split=inputs["split"],
    model=inputs["model"],
    groups=inputs["groups"],
    reconstruction_quality=inputs["reconstruction_quality"],
    grouping_quality=inputs["grouping_quality"],
    forecasts={m: inputs[f"forecast_{m}"] for m in snakemake.params.methods},
    benchmarks={k[len("bench_") :]: v for k, v in inputs.items() if k.startswith("bench_")},
    out_metrics=snakemake.output.metrics,
    out_renders=snakemake.output.renders,
    params=snakemake.params.evaluate,
    variant=snakemake.params.variant,
    ids=dict(snakemake.wildcards.items()),
)
