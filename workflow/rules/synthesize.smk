# The embedded synthetic scene, written in the DyCheck iPhone layout with
# ground truth, so the pipeline runs from an empty results/ folder.


rule synthesize:
    output:
        directory(artefact("synthesize")),
    log:
        log_file("synthesize"),
    wildcard_constraints:
        dataset="|".join(synthetic_datasets()),
    priority: PRIORITY["synthesize"]
    conda:
        "../../envs/mogaf.yaml"
    # frames render on two threads (the same files): every other job waits for it
    threads: 2
    params:
        synthetic=lambda wildcards: config["synthetic"][wildcards.scene],
    script:
        "../scripts/synthesize.py"
