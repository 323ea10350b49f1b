# Depth / track / mask priors on observed frames only (each only if the scene needs it).


rule priors:
    input:
        scene=scene_h5,
        split=split_h5,
    output:
        artefact("priors"),
    log:
        log_file("priors"),
    benchmark:
        benchmark_tsv("priors")
    conda:
        "../../envs/mogaf.yaml"
    params:
        priors=params_for("priors"),
        seed=seed,
    script:
        "../scripts/priors.py"
