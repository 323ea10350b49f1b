# Depth / track / mask priors on observed frames only (each only if the scene needs it).


rule priors:
    input:
        unpack(stage_inputs("priors")),
    output:
        artefact("priors"),
    log:
        log_file("priors"),
    benchmark:
        benchmark_tsv("priors")
    priority: PRIORITY["priors"]
    conda:
        "../../envs/mogaf.yaml"
    params:
        **stage_params("priors"),
    script:
        "../scripts/run_stage.py"
