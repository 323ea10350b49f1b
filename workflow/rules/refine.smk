# Group-wise refinement: L_recon + lambda_rigid L_rigid + lambda_nr L_nr (paper Sec. 4.2).


rule refine:
    input:
        unpack(refine_inputs),
    output:
        artefact("refine"),
    log:
        log_file("refine"),
    benchmark:
        benchmark_tsv("refine")
    conda:
        "../../envs/mogaf.yaml"
    # One torch thread (recon.threads): fixed float-reduction order, so artefacts are
    # bitwise reproducible; two such jobs share a 2-core machine.
    threads: 1
    resources:
        mem_mb=8000,
        runtime=120,
        gpu=lambda wildcards: 1 if device(wildcards) == "cuda" else 0,
    params:
        refine=params_for("refine"),
        seed=seed,
        device=device,
        checkpoint="results/{dataset}/{scene}/ratio{ratio}/{prefix}checkpoints/refine.pt",
    script:
        "../scripts/refine.py"
