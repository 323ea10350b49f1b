# Quality of the model the forecasts start from at held-out views at observed
# times (PSNR, SSIM; masked ones on iPhone scenes). Its own rule so that the
# variants forecasting from one model render these views once: one file per
# model, {model} = recon (recon.h5) or refined (refined.h5).


rule reconstruction_quality:
    input:
        unpack(stage_inputs("reconstruction_quality")),
    output:
        artefact("reconstruction_quality"),
    log:
        log_file("reconstruction_quality"),
    benchmark:
        benchmark_tsv("reconstruction_quality")
    priority: PRIORITY["reconstruction_quality"]
    conda:
        "../../envs/mogaf.yaml"
    # One core: the same artefact as with two (measured), no slower, and it can
    # run beside a reconstruction instead of waiting for both cores.
    threads: 1
    params:
        **stage_params("reconstruction_quality"),
    script:
        "../scripts/run_stage.py"
