# One method's forecast as PLY files in the original 3DGS layout, for
# Gaussian-splatting viewers: the model at the last observed step and the
# forecast at every forecast step (or export.steps), with index.json giving
# each file's time step, time and evaluation cameras. Opt-in (no other rule
# reads it; not part of `make demo`), e.g.
#   snakemake -c2 results/synthetic/default/ratio0.6/export/mogaf/index.json

from mogaf.export.params import ply_folder


rule export:
    input:
        model=forecast_model,
        forecast=lambda wildcards: forecast_h5(wildcards, wildcards.method),
        scene=scene_h5,
        split=split_h5,
    output:
        index=artefact("export"),
        ply=directory(ply_folder(artefact("export"))),
    log:
        log_file("export_{method}"),
    benchmark:
        benchmark_tsv("export_{method}")
    conda:
        "../../envs/mogaf.yaml"
    # one core: it converts and writes; nothing is rendered
    threads: 1
    params:
        export=params_for("export"),
    script:
        "../scripts/export.py"
