# The forecast split, made once: observed frames, forecast times, evaluation views.
# Every later stage reads only the frames this artefact gives it.


rule split:
    input:
        scene=scene_h5,
    output:
        artefact("split"),
    log:
        "results/{dataset}/{scene}/ratio{ratio}/logs/split.log",
    conda:
        "../../envs/mogaf.yaml"
    script:
        "../scripts/split.py"
