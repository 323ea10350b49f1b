# Group-wise motion forecasting (paper Sec. 4.3): one job per dynamic group and
# trained method (one job "all" when forecast.groupwise is off), merged into
# forecast/{method}.h5. Static groups keep their last pose; constant velocity
# and frozen train nothing and are computed in the merge job.


rule forecast_group:
    input:
        model=forecast_model,
        groups=groups_h5,
        split=split_h5,
    output:
        "results/{dataset}/{scene}/ratio{ratio}/{prefix}forecast/{method}/group{group}.h5",
    log:
        "results/{dataset}/{scene}/ratio{ratio}/{prefix}logs/forecast_{method}_group{group}.log",
    benchmark:
        "results/{dataset}/{scene}/ratio{ratio}/{prefix}benchmarks/forecast_{method}_group{group}.tsv"
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
        "../scripts/forecast_group.py"


rule forecast:
    input:
        model=forecast_model,
        groups=groups_h5,
        split=split_h5,
        parts=forecast_part_files,
    output:
        "results/{dataset}/{scene}/ratio{ratio}/{prefix}forecast/{method}.h5",
    log:
        "results/{dataset}/{scene}/ratio{ratio}/{prefix}logs/forecast_{method}.log",
    benchmark:
        "results/{dataset}/{scene}/ratio{ratio}/{prefix}benchmarks/forecast_{method}.tsv"
    conda:
        "../../envs/mogaf.yaml"
    params:
        forecast=forecast_params,
        seed=seed,
    script:
        "../scripts/forecast_merge.py"
