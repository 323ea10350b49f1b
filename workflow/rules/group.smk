# Motion-aware Gaussian grouping (paper Sec. 4.1, Algorithm 3; Gaga-4D baseline).
# A checkpoint: which rigid/dynamic groups exist decides the jobs downstream.


checkpoint group:
    input:
        unpack(stage_inputs("group")),
    output:
        artefact("group"),
    log:
        log_file("group"),
    benchmark:
        benchmark_tsv("group")
    priority: PRIORITY["group"]
    conda:
        "../../envs/mogaf.yaml"
    # One core: the same artefact as with two (measured), no slower, and it can
    # run beside a reconstruction instead of waiting for both cores.
    threads: 1
    params:
        **stage_params("group"),
    script:
        "../scripts/run_stage.py"
