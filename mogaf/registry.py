"""The stage graph, written once.

Each StageSpec describes one pipeline stage completely: the artefacts it
reads (and which stage makes each), the artefact it writes, the config
section it takes, the guards run before it and the library function that
does the work ("module:function", imported only when the stage runs, so
torch loads only then). Everything else is derived from this table:

- the generic runner (`mogaf.stages.run`, and `mogaf.stages.<stage>`) runs
  the guards and calls the function;
- the one Snakemake script (workflow/scripts/run_stage.py) finds the spec by
  its rule's name;
- the rules' `input:` blocks (`unpack(stage_inputs("refine"))`), `params:`
  blocks (`**stage_params("refine")`), outputs, logs, benchmarks and
  checkpoints (workflow/rules/common.smk);
- the CLI's subcommands (mogaf.cli);
- which artefacts an ablation variant shares (mogaf.config).

Adding a stage is one spec here, one rule file and one library package
(docs/pipeline.md, "Adding a stage").

Paths: `output` is relative to the folder of one scene, ratio and variant,
results/{dataset}/{scene}/ratio{r}/{prefix} (`scope` says which folder:
the scene's, the ratio's or the variant's). Every path pattern of a job (its
artefact, log, benchmark and training checkpoint) comes from the functions
at the end of this module.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

RESULTS = "results"
RATIO_DIR = RESULTS + "/{dataset}/{scene}/ratio{ratio}/"
SCENE_DIR = RESULTS + "/{dataset}/{scene}/"
TABLES_DIR = RESULTS + "/tables/"
# scope -> the folder a stage's artefact, logs/, benchmarks/ and checkpoints/ go in
SCOPE_DIRS = {
    "scene": SCENE_DIR,  # one per scene, before the split
    "ratio": RATIO_DIR,  # one per ratio, shared by every variant (the split)
    "variant": RATIO_DIR + "{prefix}",  # {prefix}: '' or ablation/<variant>/ (mogaf.config.artefact_prefix)
    "tables": TABLES_DIR,  # the tables of every result
}
# what a job writes besides its artefact: kind -> (folder, suffix)
JOB_FILES = {"log": ("logs", ".log"), "benchmark": ("benchmarks", ".tsv"), "checkpoint": ("checkpoints", ".pt")}

# A source that is not a fixed stage: fn(config of the scene and variant, wildcards) -> stage name.
Source = Callable[[Mapping[str, Any], Any], str]


def forecast_input(cfg: Mapping[str, Any], wildcards: Any) -> str:
    """The model the forecasts start from: refined.h5, or recon.h5 (forecast.input: recon)."""
    from .config import forecast_input_stage

    return forecast_input_stage(cfg)


def measured_model(cfg: Mapping[str, Any], wildcards: Any) -> str:
    """The model reconstruction_quality measures: its {model} wildcard (recon or refined)."""
    return {"recon": "recon", "refined": "refine"}[wildcards.model]


@dataclass(frozen=True)
class Input:
    """One input of a stage: the library function's argument (and the rule's
    input name), the stage whose artefact it is, its CLI option."""

    argument: str
    # the stage writing it (its spec name), a Source, or None: the rule file gives it (a dataset folder, a list)
    source: str | Source | None
    option: str = ""  # CLI option; default `<argument>-h5` (underscores as dashes)
    required: bool = True
    checkpoint: bool = False  # read after the source's checkpoint rule has run (Snakemake re-evaluates the DAG)
    # ("module:predicate", argument): given only when predicate(path of that other input) holds
    only_if: tuple[str, str] | None = None
    many: bool = False  # a list of paths

    @property
    def cli_option(self) -> str:
        return self.option or self.argument.replace("_", "-") + "-h5"


@dataclass(frozen=True)
class Output:
    """A further output beside the artefact: a file or folder next to it."""

    role: str  # its name in the rule's output and in the output checks
    argument: str  # the function's argument; left out, it is `sibling` beside the artefact
    sibling: str
    directory: bool = False  # a folder the stage replaces whole


@dataclass(frozen=True)
class Guard:
    """A check run before the stage's function: `check` ("module:function")
    is called with the stage's `arguments`; it raises MogafError."""

    check: str
    arguments: tuple[str, ...]
    before_inputs: bool = False  # before the inputs are opened (lineage); else inside mogaf.artefact.stage_inputs


# the guards the stages share (mogaf.stages)
GROUPS_COVER = "mogaf.stages:check_groups_cover"  # groups.h5 gives a group to every Gaussian of the model
MADE_FROM = "mogaf.artefact:check_made_from"  # the first input was made from the second itself
RATIO = "mogaf.stages:check_ratio_text"  # the {ratio} of the target path is a number in (0, 1)


@dataclass(frozen=True)
class StageSpec:
    """One stage. The generic runner (mogaf.stages.run) checks the outputs
    (mogaf.paths.check_outputs: no input overwritten, nothing written into a
    dataset), runs the `before_inputs` guards, opens the inputs' lineage
    (mogaf.artefact.stage_inputs: one lineage, recorded in what it writes),
    runs the other guards and calls

        function(*inputs, out, params, **wildcards, **config values,
                 checkpoint=..., **further outputs, **fixed)

    (`params` only with `settings`; the inputs in their order here)."""

    name: str  # the rule's name (the part before ':') and the key of its artefact in mogaf.config's tables
    function: str | None = None  # "module:function" the generic runner calls
    # a dedicated entry point in mogaf.stages instead of the generic runner (it does its own checks)
    wrapper: str | None = None
    output: str | None = None  # artefact file (pattern) relative to the scope's folder
    inputs: tuple[Input, ...] = ()
    output_argument: str = "out"  # the function's argument holding the output path
    outputs: tuple[Output, ...] = ()  # further outputs
    settings: str | None = None  # config section passed as `params`
    # its settings dataclass ("module:Class"): mogaf.settings.SECTIONS and the config schema list it from here
    settings_class: str | None = None
    seed: str | None = None  # the config's `seed`: "params" (merged into params), "kwarg" or None
    device: str | None = None  # the config's `device`, likewise
    checkpoint: bool = False  # takes a resumable training checkpoint (`checkpoint`)
    wildcards: tuple[str, ...] = ()  # wildcards of the target path passed as arguments (CLI options)
    guards: tuple[Guard, ...] = ()
    fixed: tuple[tuple[str, Any], ...] = ()  # constant keyword arguments of the function
    # torch's thread count follows the rule's `threads` (False: the stage never imports torch, or runs
    # with torch's default as it always did)
    torch_threads: bool = True
    # the rule's `threads` (the CLI's --threads) passed as `job_threads`, for a stage that sets torch's count only where it uses torch
    threads_argument: bool = False
    # What determines the artefact besides its upstream stages: config keys
    # (dotted); None: the stage is never shared across variants by this table.
    digest_sections: tuple[str, ...] | None = None
    upstream: tuple[str, ...] = ()
    scope: str = "variant"  # the folder of its files: SCOPE_DIRS
    variant_key: str | None = None  # its key in mogaf.config's variant tables, when not its name
    rule_output: str | None = None  # the rule's output pattern, when one rule writes several specs' artefacts
    job: str | None = None  # the name of its jobs' log and benchmark files (default: the rule's)
    runtime: bool = False  # its wall time counts in the run time of the results made from it (metrics.json)
    cli: str | None = None  # its `python -m mogaf` subcommand

    @property
    def rule(self) -> str:
        return self.name.split(":", 1)[0]

    @property
    def seeded(self) -> bool:
        return self.seed is not None

    @property
    def uses_device(self) -> bool:
        return self.device is not None

    @property
    def per_scene(self) -> bool:
        return self.scope == "scene"

    @property
    def generic(self) -> bool:
        return self.wrapper is None


def _in(argument: str, source: str | Source | None, **kw: Any) -> Input:
    return Input(argument, source, **kw)


SCENE = _in("scene", "ingest")
SCENE_OPTIONAL = _in("scene", "ingest", required=False)
SPLIT = _in("split", "split")
PRIORS = _in("priors", "priors")
PRIORS_OPTIONAL = _in("priors", "priors", required=False)
# A forecast job's inputs. The scene: the observed frames' camera poses
# (structured MoGaF's unobserved_motion); the priors: the 2D tracks at two
# observed steps (its track_agreement).
FORECAST_INPUTS = (
    _in("model", forecast_input),
    _in("groups", "group", checkpoint=True),
    SPLIT,
    SCENE_OPTIONAL,
    PRIORS_OPTIONAL,
)

STAGES: tuple[StageSpec, ...] = (
    StageSpec(
        "synthesize",
        wrapper="synthesize",
        output="source",
        output_argument="out_dir",
        scope="scene",
        cli="synthesize",
        threads_argument=True,
    ),
    StageSpec(
        "ingest",
        wrapper="ingest",
        output="scene.h5",
        scope="scene",
        inputs=(_in("folder", None, option="folder"),),
        wildcards=("dataset", "scene"),
        runtime=True,
        cli="ingest",
    ),
    StageSpec(
        "split",
        function="mogaf.stages:split_stage",
        output="split.h5",
        scope="ratio",
        inputs=(SCENE,),
        wildcards=("ratio",),
        guards=(Guard(RATIO, ("ratio",), before_inputs=True),),
        torch_threads=False,
        cli="split",
    ),
    StageSpec(
        "priors",
        function="mogaf.priors.stage:run_priors_stage",
        output="priors.h5",
        inputs=(SCENE, SPLIT),
        settings="priors",
        settings_class="mogaf.priors.params:PriorsSettings",
        seed="params",
        torch_threads=False,
        digest_sections=("seed", "priors"),
        runtime=True,
        cli="priors",
    ),
    StageSpec(
        "recon",
        function="mogaf.recon.stage:run_recon_stage",
        output="recon.h5",
        inputs=(SCENE, SPLIT, PRIORS),
        settings="recon",
        settings_class="mogaf.recon.params:ReconSettings",
        seed="kwarg",
        device="params",
        checkpoint=True,
        fixed=(("progress", False),),
        digest_sections=("seed", "device", "recon"),
        upstream=("priors",),
        runtime=True,
        cli="recon",
    ),
    StageSpec(
        "group",
        function="mogaf.grouping.stage:run_group_stage",
        output="groups.h5",
        inputs=(_in("model", "recon"), PRIORS, SCENE),
        settings="grouping",
        settings_class="mogaf.grouping.params:GroupingSettings",
        seed="params",
        torch_threads=False,
        digest_sections=("grouping",),
        upstream=("recon", "priors"),
        runtime=True,
        cli="group",
    ),
    StageSpec(
        "rigid_init",
        function="mogaf.grouping.stage:run_rigid_init_stage",
        output="rigid.h5",
        inputs=(_in("model", "recon"), _in("groups", "group")),
        settings="rigid_init",
        settings_class="mogaf.grouping.params:RigidInitSettings",
        guards=(Guard(GROUPS_COVER, ("model", "groups")),),
        torch_threads=False,
        digest_sections=("rigid_init",),
        upstream=("group",),
        runtime=True,
        cli="rigid-init",
    ),
    StageSpec(
        "refine",
        function="mogaf.refine.stage:run_refine_stage",
        output="refined.h5",
        inputs=(
            _in("model", "recon"),
            # after the checkpoint: rigid.h5 only when there are rigid groups
            _in("groups", "group", checkpoint=True),
            _in("rigid", "rigid_init", required=False, only_if=("mogaf.grouping.core:has_rigid_groups", "groups")),
            PRIORS,
            SCENE,
            SPLIT,
        ),
        settings="refine",
        settings_class="mogaf.refine.params:RefineSettings",
        seed="kwarg",
        device="params",
        checkpoint=True,
        fixed=(("progress", False),),
        guards=(Guard(GROUPS_COVER, ("model", "groups")),),
        digest_sections=("seed", "device", "refine"),
        upstream=("recon", "group", "rigid_init"),
        runtime=True,
        cli="refine",
    ),
    StageSpec(
        "grouping_quality",
        function="mogaf.grouping.quality:run_grouping_quality_stage",
        output="grouping_quality.h5",
        inputs=(_in("grouped_model", "recon"), _in("groups", "group"), SCENE, SPLIT),
        settings="grouping_quality",
        settings_class="mogaf.grouping.params:GroupingQualitySettings",
        guards=(Guard(GROUPS_COVER, ("grouped_model", "groups")),),
        digest_sections=("grouping_quality",),
        upstream=("group", "recon"),
        cli="grouping-quality",
    ),
    # one rule, one artefact per model ({model}: recon, refined), so the
    # variants forecasting from one model share it
    *(
        StageSpec(
            f"reconstruction_quality:{stage}",
            function="mogaf.reconstruction_quality.stage:run_reconstruction_quality_stage",
            output=f"reconstruction_quality/{model}.h5",
            rule_output="reconstruction_quality/{model}.h5",
            job="reconstruction_quality_{model}",
            inputs=(_in("model", measured_model), SCENE, SPLIT),
            settings="reconstruction_quality",
            settings_class="mogaf.reconstruction_quality.params:ReconstructionQualitySettings",
            digest_sections=("reconstruction_quality",),
            upstream=(stage,),
            cli="reconstruction-quality" if stage == "recon" else None,
        )
        for stage, model in (("recon", "recon"), ("refine", "refined"))
    ),
    # A forecast's sections and upstream depend on the method and the config
    # (mogaf.config._sections / _upstream); one job per motion group, merged.
    # Dedicated wrappers: mogaf.forecast is refactored on its own schedule.
    StageSpec(
        "forecast_group",
        wrapper="forecast_group",
        output="forecast/{method}/group{group}.h5",
        inputs=FORECAST_INPUTS,
        settings="forecast",
        seed="kwarg",
        device="kwarg",
        wildcards=("method", "group"),
        variant_key="forecast:{method}",
        job="forecast_{method}_group{group}",
        cli="forecast-group",
    ),
    StageSpec(
        "forecast",
        wrapper="forecast_merge",
        output="forecast/{method}.h5",
        # parts: forecast/{method}/group{k}.h5 of the method's jobs (the rule lists them)
        inputs=(*FORECAST_INPUTS, _in("parts", None, option="parts", required=False, many=True)),
        settings="forecast",
        seed="kwarg",
        device="kwarg",
        wildcards=("method",),
        torch_threads=False,
        threads_argument=True,
        variant_key="forecast:{method}",
        job="forecast_{method}",
        cli="forecast",
    ),
    StageSpec(
        "evaluate",
        wrapper="evaluate",
        output="metrics.json",
        output_argument="out_metrics",
        outputs=(Output("renders", "out_renders", "renders", directory=True),),
        settings="evaluate",
        settings_class="mogaf.evaluate.params:EvaluateSettings",
        digest_sections=("evaluate", "forecast.methods"),
    ),
    # opt-in, no stage reads it: one method's forecast as 3DGS PLY files
    # (ply/ beside index.json, mogaf.export.ply_folder) for Gaussian-splatting viewers
    StageSpec(
        "export",
        function="mogaf.export.stage:run_export_stage",
        output="export/{method}/index.json",
        outputs=(Output("ply", "ply_dir", "ply", directory=True),),
        inputs=(_in("model", forecast_input), _in("forecast", "forecast"), SCENE, SPLIT),
        settings="export",
        settings_class="mogaf.export.params:ExportSettings",
        # poses of this very model's Gaussians (refined.h5 vs recon.h5)
        guards=(Guard(MADE_FROM, ("forecast", "model")),),
        job="export_{method}",
        cli="export",
    ),
)

BY_NAME: dict[str, StageSpec] = {spec.name: spec for spec in STAGES}


def register(new: StageSpec) -> StageSpec:
    """Add a stage at run time (a plugin, a test); a spec of that name is replaced."""
    global STAGES
    STAGES = tuple(s for s in STAGES if s.name != new.name) + (new,)
    BY_NAME[new.name] = new
    return new


def unregister(name: str) -> None:
    global STAGES
    STAGES = tuple(s for s in STAGES if s.name != name)
    BY_NAME.pop(name, None)


def spec(name: str) -> StageSpec:
    """A stage by its name, or by its rule's name (reconstruction_quality: its first spec)."""
    if name in BY_NAME:
        return BY_NAME[name]
    for s in STAGES:
        if s.rule == name:
            return s
    raise KeyError(f"no stage {name!r} in mogaf.registry (known: {', '.join(BY_NAME)})")


def by_command(command: str) -> StageSpec:
    return next(s for s in STAGES if s.cli == command)


def commands() -> dict[str, StageSpec]:
    """CLI subcommand -> spec."""
    return {s.cli: s for s in STAGES if s.cli}


def load(dotted: str) -> Any:
    """'package.module:function' -> the function (imported now, not before)."""
    module, _, attr = dotted.partition(":")
    if not attr:
        raise ValueError(f"{dotted!r} is not 'module:function'")
    return getattr(importlib.import_module(module), attr)


# ------------------------------------------------------------------ tables of mogaf.config
def artefact_files() -> dict[str, str]:
    """stage -> its artefact, relative to the ratio folder (stages with one per ratio)."""
    return {s.name: s.output for s in STAGES if s.output and not s.per_scene and s.digest_sections is not None}


def digest_sections() -> dict[str, tuple[str, ...]]:
    return {s.name: s.digest_sections for s in STAGES if s.digest_sections is not None}


def upstream() -> dict[str, tuple[str, ...]]:
    """Fixed upstream stages (forecast and evaluate follow the config: mogaf.config)."""
    return {s.name: s.upstream for s in STAGES if s.digest_sections is not None and s.name != "evaluate"}


# ------------------------------------------------------------------ path patterns
def stage_dir(name: str, scope: str | None = None) -> str:
    """The folder pattern of a stage's (or another rule's) files: its scope's folder."""
    if scope is None:
        scope = BY_NAME[name].scope if name in BY_NAME else next((s.scope for s in STAGES if s.rule == name), "variant")
    return SCOPE_DIRS[scope]


def rule_output(name: str, role: str | None = None) -> str:
    """The path pattern a stage's rule writes (Snakemake wildcards), or its further output `role`.
    A spec name gives its artefact; a rule writing several specs' artefacts its rule_output."""
    s = spec(name)
    output = s.output if name == s.name else s.rule_output or s.output
    if output is None:
        raise KeyError(f"stage {name} has no artefact")
    if role is not None:
        further = {o.role: o for o in s.outputs}
        if role not in further:
            raise KeyError(f"stage {name} has no output {role!r}")
        output = sibling(output, further[role].sibling)
    return stage_dir(s.name) + output


def sibling(path: str, name: str) -> str:
    """`name` in the folder of `path` (a further output beside the artefact)."""
    head, sep, _ = path.rpartition("/")
    return f"{head}{sep}{name}"


def job_name(name: str) -> str:
    """The name pattern of a rule's log and benchmark files (e.g. forecast_{method}_group{group})."""
    try:
        s = spec(name)
    except KeyError:
        return name
    return s.job or s.rule


def job_path(kind: str, name: str, scope: str | None = None) -> str:
    """The path pattern of a job's log, benchmark or training checkpoint
    (`kind`: JOB_FILES) of stage or rule `name`, in its scope's folder."""
    folder, suffix = JOB_FILES[kind]
    job = name if kind == "checkpoint" else job_name(name)
    return f"{stage_dir(name, scope)}{folder}/{job}{suffix}"
