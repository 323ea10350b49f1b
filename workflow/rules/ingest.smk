# Read a dataset folder into one scene model: results/{dataset}/{scene}/scene.h5


rule ingest:
    input:
        dataset_folder,
    output:
        artefact("ingest"),
    log:
        log_file("ingest"),
    benchmark:
        benchmark_tsv("ingest")
    priority: PRIORITY["ingest"]
    conda:
        "../../envs/mogaf.yaml"
    params:
        layout=lambda wildcards: mcfg.dataset_layout(config, wildcards.dataset),
        options=lambda wildcards: mcfg.ingest_options(config, wildcards.dataset, wildcards.scene),
    script:
        "../scripts/ingest.py"
