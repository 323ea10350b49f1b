# 4D Gaussian reconstruction (Shape-of-Motion representation) on observed frames.
# Its training checkpoint (params.checkpoint) survives a killed job, so a rerun resumes.


rule recon:
    input:
        unpack(stage_inputs("recon")),
    output:
        artefact("recon"),
    log:
        log_file("recon"),
    benchmark:
        benchmark_tsv("recon")
    priority: PRIORITY["recon"]
    conda:
        "../../envs/mogaf.yaml"
    # One torch thread (recon.threads): fixed float-reduction order, so artefacts are
    # bitwise reproducible; two such jobs share a 2-core machine. The rasterizer also
    # takes a core left idle (mogaf.cores; same bits).
    threads: 1
    resources:
        mem_mb=8000,
        runtime=240,
        gpu=lambda wildcards: 1 if device(wildcards) == "cuda" else 0,
    params:
        **stage_params("recon"),
    script:
        "../scripts/run_stage.py"
