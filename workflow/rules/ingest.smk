# Read a dataset folder into one scene model: results/{dataset}/{scene}/scene.h5


rule ingest:
    input:
        dataset_folder,
    output:
        "results/{dataset}/{scene}/scene.h5",
    params:
        layout=lambda wildcards: mcfg.dataset_layout(config, wildcards.dataset),
        options=lambda wildcards: mcfg.ingest_options(config, wildcards.dataset, wildcards.scene),
    log:
        "results/{dataset}/{scene}/logs/ingest.log",
    benchmark:
        "results/{dataset}/{scene}/benchmarks/ingest.tsv"
    conda:
        "../../envs/mogaf.yaml"
    script:
        "../scripts/ingest.py"
