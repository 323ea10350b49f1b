# Rigid initialisation: per rigid group and observed time, Procrustes (uniform
# weights as in the paper, or opacity-weighted: rigid_init.weights).
# Never runs for a scene without rigid groups (see refine's input function).


rule rigid_init:
    input:
        model=lambda wildcards: stage_path("recon", wildcards),
        groups=lambda wildcards: stage_path("group", wildcards),
    output:
        artefact("rigid_init"),
    log:
        log_file("rigid_init"),
    benchmark:
        benchmark_tsv("rigid_init")
    conda:
        "../../envs/mogaf.yaml"
    params:
        rigid_init=params_for("rigid_init"),
    script:
        "../scripts/rigid_init.py"
