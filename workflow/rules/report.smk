# Tables in the layout of the paper (Markdown, LaTeX, CSV) and error against run
# time, regenerated from whatever metrics.json files exist (plus the demo's and
# the grid's, which are computed first when missing).


rule tables:
    input:
        configured_metrics,
    output:
        # HTML in the report: it shows HTML inline, Markdown only as a download
        report(
            multiext(
                "results/tables/table_",
                "forecast.html",
                "iphone.html",
                "dnerf.html",
                "grouping.html",
                "groupwise.html",
                "masking.html",
            ),
            caption="../report/tables.rst",
            category="Tables",
        ),
        multiext(
            "results/tables/table_",
            "forecast.md",
            "iphone.md",
            "dnerf.md",
            "grouping.md",
            "groupwise.md",
            "masking.md",
        ),
        multiext(
            "results/tables/table_",
            "forecast.tex",
            "iphone.tex",
            "dnerf.tex",
            "grouping.tex",
            "groupwise.tex",
            "masking.tex",
        ),
        multiext(
            "results/tables/table_",
            "forecast.csv",
            "iphone.csv",
            "dnerf.csv",
            "grouping.csv",
            "groupwise.csv",
            "masking.csv",
        ),
    log:
        log_file("tables", scope="tables"),
    conda:
        "../../envs/mogaf.yaml"
    params:
        report=config["report"],
        ablations=ABLATIONS,
        other_metrics=other_metrics(),
    script:
        "../scripts/tables.py"


rule runtime_report:
    input:
        configured_metrics,
    output:
        csv="results/tables/error_vs_runtime.csv",
        md="results/tables/error_vs_runtime.md",
        png=report("results/tables/error_vs_runtime.png", caption="../report/runtime.rst", category="Error vs run time"),
    log:
        log_file("runtime_report", scope="tables"),
    conda:
        "../../envs/mogaf.yaml"
    params:
        report=runtime_report_params(),
        other_metrics=other_metrics(),
    script:
        "../scripts/runtime_report.py"


# A scene's forecast videos on one page and the quality of the model its
# forecasts start from, for the report (`make report`).
rule scene_report:
    input:
        unpack(scene_report_inputs),
    output:
        # a folder with its page: only a zipped report holds it (mogaf/report/pages.py)
        videos=report(
            directory("results/{dataset}/{scene}/ratio{ratio}/{prefix}report/videos"),
            htmlindex="index.html",
            caption="../report/renders.rst",
            category="Forecast videos",
        ),
        quality=report(
            "results/{dataset}/{scene}/ratio{ratio}/{prefix}report/quality.png",
            caption="../report/quality.rst",
            category="Grouping and reconstruction quality",
        ),
    log:
        log_file("scene_report"),
    conda:
        "../../envs/mogaf.yaml"
    script:
        "../scripts/scene_report.py"


# One target per sweep of config/ablations.yaml: `snakemake -c2 sweep_<name>`.
for _sweep in ABLATIONS.get("sweeps", {}):

    rule:
        name:
            f"sweep_{_sweep}"
        input:
            sweep_targets(_sweep),
        localrule: True


# `snakemake -c2 scenes`: one table per ratio, a row per scene of the config's
# grid (config/family.yaml: the scene family), every method's PSNR / LPIPS and
# tracking EPE, and MoGaF's margin over the better of frozen and constant velocity.
rule scenes:
    input:
        grid_targets(),
    output:
        "results/tables/scenes.md",
    log:
        log_file("scenes", scope="tables"),
    conda:
        "../../envs/mogaf.yaml"
    script:
        "../scripts/scenes_table.py"
