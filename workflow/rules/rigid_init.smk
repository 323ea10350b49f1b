# Rigid initialisation: per rigid group and observed time, Procrustes (uniform
# weights as in the paper, or opacity-weighted: rigid_init.weights).
# Never runs for a scene without rigid groups (see refine's input function).


rule rigid_init:
    input:
        model=lambda wildcards: stage_path("recon", wildcards),
        groups=lambda wildcards: stage_path("group", wildcards),
    output:
        "results/{dataset}/{scene}/ratio{ratio}/{prefix}rigid.h5",
    params:
        rigid_init=params_for("rigid_init"),
    log:
        log_file("rigid_init"),
    benchmark:
        benchmark_tsv("rigid_init")
    conda:
        "../../envs/mogaf.yaml"
    script:
        "../scripts/rigid_init.py"
