# Render forecasts at the evaluation views; image, tracking and grouping metrics,
# wall time and memory of every stage that produced them.


rule evaluate:
    input:
        unpack(evaluate_inputs),
    output:
        metrics=artefact("evaluate"),
        # in the report through the scene_report rule's page (the report plays HTML inline)
        renders=directory(artefact("evaluate", "renders")),
    log:
        log_file("evaluate"),
    benchmark:
        benchmark_tsv("evaluate")
    conda:
        "../../envs/mogaf.yaml"
    # One core: a two-core job waits until both are free (a sweep's evaluation then
    # missed a core idle during refinement). Forecasts are measured side by side on
    # cores left idle (mogaf.cores; the same files).
    threads: 1
    params:
        evaluate=params_for("evaluate"),
        methods=lambda wildcards: scene_cfg(wildcards)["forecast"]["methods"],
        variant=lambda wildcards: variant_of(wildcards) or "default",
    script:
        "../scripts/evaluate.py"
