# One method's forecast as PLY files in the original 3DGS layout, for
# Gaussian-splatting viewers: the model at the last observed step and the
# forecast at every forecast step (or export.steps), with index.json giving
# each file's time step, time and evaluation cameras. Opt-in (no other rule
# reads it; not part of `make demo`), e.g.
#   snakemake -c2 results/synthetic/default/ratio0.6/export/mogaf/index.json


rule export:
    input:
        unpack(stage_inputs("export")),
    output:
        index=artefact("export"),
        ply=directory(artefact("export", "ply")),
    log:
        log_file("export"),
    benchmark:
        benchmark_tsv("export")
    conda:
        "../../envs/mogaf.yaml"
    # one core: it converts and writes; nothing is rendered
    threads: 1
    params:
        **stage_params("export"),
    script:
        "../scripts/run_stage.py"
