# MoGaF: motion group-aware Gaussian forecasting as a cached pipeline.
# Target grammar: results/{dataset}/{scene}/ratio{r}/<artefact>
#   e.g. snakemake -c2 results/synthetic/default/ratio0.6/metrics.json
# See docs/pipeline.md for the stages and config/README.md for every setting.
from snakemake.utils import min_version

min_version("9.0")


configfile: "config/config.yaml"


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/synthesize.smk"
include: "workflow/rules/ingest.smk"
include: "workflow/rules/split.smk"
include: "workflow/rules/priors.smk"
include: "workflow/rules/recon.smk"
include: "workflow/rules/group.smk"
include: "workflow/rules/rigid_init.smk"
include: "workflow/rules/refine.smk"
include: "workflow/rules/forecast.smk"
include: "workflow/rules/grouping_quality.smk"
include: "workflow/rules/reconstruction_quality.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/report.smk"
include: "workflow/rules/export.smk"


localrules:
    all,
    demo,
    tables,
    runtime_report,


rule all:
    default_target: True
    input:
        grid_targets(),
        "results/tables/table_dnerf.md",
        "results/tables/error_vs_runtime.png",


# README command 1 (`make demo`): the embedded synthetic scene end to end,
# every method, the tables and the error-vs-run-time plot.
rule demo:
    input:
        demo_targets(),
