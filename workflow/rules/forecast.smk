# Group-wise motion forecasting (paper Sec. 4.3): one job per dynamic group and
# trained method (one job "all" when forecast.groupwise is off), merged into
# forecast/{method}.h5. Static groups keep their last pose; constant velocity
# and frozen train nothing and are computed in the merge job, as every method
# is under forecast.jobs: per_method. Their params are only what one method's
# forecast depends on (forecast_params), not the whole forecast section.


rule forecast_group:
    input:
        unpack(stage_inputs("forecast_group")),
    output:
        artefact("forecast_group"),
    log:
        log_file("forecast_group"),
    benchmark:
        benchmark_tsv("forecast_group")
    priority: forecast_priority("forecast_group")
    conda:
        "../../envs/mogaf.yaml"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=30,
        gpu=lambda wildcards: 1 if device(wildcards) == "cuda" else 0,
    params:
        forecast=forecast_params,
        seed=seed,
        device=device,
    script:
        "../scripts/run_stage.py"


rule forecast:
    input:
        unpack(stage_inputs("forecast")),
        parts=forecast_part_files,
    output:
        artefact("forecast"),
    log:
        log_file("forecast"),
    benchmark:
        benchmark_tsv("forecast")
    priority: forecast_priority("forecast")
    conda:
        "../../envs/mogaf.yaml"
    threads: 1
    resources:
        mem_mb=forecast_merge_mem_mb,
        runtime=forecast_merge_runtime,
        gpu=forecast_merge_gpus,
    params:
        forecast=forecast_merge_params,
        seed=seed,
    script:
        "../scripts/run_stage.py"
