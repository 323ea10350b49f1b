"""Every rule of a stage in mogaf.registry that has no script of its own:
mogaf.stages.run_rule finds the stage by the rule's name and runs it from
the job's inputs, outputs, params and wildcards."""

from mogaf.stages import run_rule

run_rule(snakemake)
