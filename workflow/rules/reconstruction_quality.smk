# Quality of the model the forecasts start from at held-out views at observed
# times (PSNR, SSIM; masked ones on iPhone scenes). Its own rule so that the
# variants forecasting from one model render these views once: one file per
# model, {model} = recon (recon.h5) or refined (refined.h5).


rule reconstruction_quality:
    input:
        model=quality_model,
        scene=scene_h5,
        split=split_h5,
    output:
        "results/{dataset}/{scene}/ratio{ratio}/{prefix}reconstruction_quality/{model}.h5",
    log:
        log_file("reconstruction_quality_{model}"),
    benchmark:
        benchmark_tsv("reconstruction_quality_{model}")
    conda:
        "../../envs/mogaf.yaml"
    # One core: the same artefact as with two (measured), no slower, and it can
    # run beside a reconstruction instead of waiting for both cores.
    threads: 1
    params:
        reconstruction_quality=params_for("reconstruction_quality"),
    script:
        "../scripts/reconstruction_quality.py"
