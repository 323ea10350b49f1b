# Group-wise refinement: L_recon + lambda_rigid L_rigid + lambda_nr L_nr (paper Sec. 4.2).


rule refine:
    input:
        unpack(stage_inputs("refine")),
    output:
        artefact("refine"),
    log:
        log_file("refine"),
    benchmark:
        benchmark_tsv("refine")
    priority: PRIORITY["refine"]
    conda:
        "../../envs/mogaf.yaml"
    # One torch thread (recon.threads): fixed float-reduction order, so artefacts are
    # bitwise reproducible; two such jobs share a 2-core machine. The rasterizer also
    # takes a core left idle (mogaf.cores; same bits).
    threads: 1
    resources:
        mem_mb=8000,
        runtime=120,
        gpu=lambda wildcards: 1 if device(wildcards) == "cuda" else 0,
    params:
        **stage_params("refine"),
    script:
        "../scripts/run_stage.py"
