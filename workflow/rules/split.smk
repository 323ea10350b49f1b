# The forecast split, made once: observed frames, forecast times, evaluation views.
# Every later stage reads only the frames this artefact gives it.


rule split:
    input:
        unpack(stage_inputs("split")),
    output:
        artefact("split"),
    log:
        log_file("split"),
    priority: PRIORITY["split"]
    conda:
        "../../envs/mogaf.yaml"
    script:
        "../scripts/run_stage.py"
