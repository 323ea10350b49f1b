# Rigid initialisation: per rigid group and observed time, Procrustes (uniform
# weights as in the paper, or opacity-weighted: rigid_init.weights).
# Never runs for a scene without rigid groups (refine's rigid input: mogaf.registry).


rule rigid_init:
    input:
        unpack(stage_inputs("rigid_init")),
    output:
        artefact("rigid_init"),
    log:
        log_file("rigid_init"),
    benchmark:
        benchmark_tsv("rigid_init")
    priority: PRIORITY["rigid_init"]
    conda:
        "../../envs/mogaf.yaml"
    params:
        **stage_params("rigid_init"),
    script:
        "../scripts/run_stage.py"
