# 4D Gaussian reconstruction (Shape-of-Motion representation) on observed frames.


rule recon:
    input:
        scene=scene_h5,
        split=split_h5,
        priors=lambda wildcards: stage_path("priors", wildcards),
    output:
        artefact("recon"),
    log:
        log_file("recon"),
    benchmark:
        benchmark_tsv("recon")
    conda:
        "../../envs/mogaf.yaml"
    # One torch thread (recon.threads): fixed float-reduction order, so artefacts are
    # bitwise reproducible; two such jobs share a 2-core machine.
    threads: 1
    resources:
        mem_mb=8000,
        runtime=240,
        gpu=lambda wildcards: 1 if device(wildcards) == "cuda" else 0,
    params:
        recon=params_for("recon"),
        seed=seed,
        device=device,
        # Survives a killed job so a rerun resumes instead of starting over.
        checkpoint="results/{dataset}/{scene}/ratio{ratio}/{prefix}checkpoints/recon.pt",
    script:
        "../scripts/recon.py"
