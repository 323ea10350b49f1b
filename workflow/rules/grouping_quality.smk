# Grouping quality against GT instance masks at held-out views at observed
# times (per-object IoU, ARI; Supp. grouping ablation). Its own rule so that
# the variants sharing one grouping render these views once.


rule grouping_quality:
    input:
        grouped_model=lambda wildcards: stage_path("recon", wildcards),
        groups=lambda wildcards: stage_path("group", wildcards),
        scene=scene_h5,
        split=split_h5,
    output:
        artefact("grouping_quality"),
    log:
        log_file("grouping_quality"),
    benchmark:
        benchmark_tsv("grouping_quality")
    conda:
        "../../envs/mogaf.yaml"
    # One core: the same artefact as with two (measured), no slower, and it can
    # run beside a reconstruction instead of waiting for both cores.
    threads: 1
    params:
        grouping_quality=params_for("grouping_quality"),
    script:
        "../scripts/grouping_quality.py"
