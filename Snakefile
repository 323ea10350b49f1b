# MoGaF: motion group-aware Gaussian forecasting as a cached pipeline.
# Target grammar: results/{dataset}/{scene}/ratio{r}/<artefact>
#   e.g. snakemake -c2 results/synthetic/default/ratio0.6/metrics.json
# See docs/pipeline.md for the stages and config/README.md for every setting.
from pathlib import Path

from snakemake.utils import min_version

min_version("9.0")


configfile: "config/config.yaml"


report: "workflow/report/workflow.rst"


# common.smk first (config, wildcards, input functions), then every rule file:
# a new stage's rule file is picked up without a line here.
include: "workflow/rules/common.smk"


for _rules in sorted(Path(workflow.basedir, "workflow", "rules").glob("*.smk")):
    if _rules.name != "common.smk":

        include: f"workflow/rules/{_rules.name}"


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
