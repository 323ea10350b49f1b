# Motion-aware Gaussian grouping (paper Sec. 4.1, Algorithm 3; Gaga-4D baseline).
# A checkpoint: which rigid/dynamic groups exist decides the jobs downstream.


checkpoint group:
    input:
        model=lambda wildcards: stage_path("recon", wildcards),
        priors=lambda wildcards: stage_path("priors", wildcards),
        scene=scene_h5,
    output:
        artefact("group"),
    log:
        log_file("group"),
    benchmark:
        benchmark_tsv("group")
    conda:
        "../../envs/mogaf.yaml"
    # One core: the same artefact as with two (measured), no slower, and it can
    # run beside a reconstruction instead of waiting for both cores.
    threads: 1
    params:
        grouping=params_for("grouping"),
        seed=seed,
    script:
        "../scripts/group.py"
