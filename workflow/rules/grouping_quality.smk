# Grouping quality against GT instance masks at held-out views at observed
# times (per-object IoU, ARI; Supp. grouping ablation). Its own rule so that
# the variants sharing one grouping render these views once.


rule grouping_quality:
    input:
        unpack(stage_inputs("grouping_quality")),
    output:
        artefact("grouping_quality"),
    log:
        log_file("grouping_quality"),
    benchmark:
        benchmark_tsv("grouping_quality")
    priority: PRIORITY["grouping_quality"]
    conda:
        "../../envs/mogaf.yaml"
    # One core: the same artefact as with two (measured), no slower, and it can
    # run beside a reconstruction instead of waiting for both cores.
    threads: 1
    params:
        **stage_params("grouping_quality"),
    script:
        "../scripts/run_stage.py"
