"""The stage graph, written once.

Each StageSpec names a pipeline stage's entry function in mogaf.stages, the
artefact it writes, the input paths it takes, the config section it reads
and the stages upstream of it. The CLI (mogaf.cli), the artefact paths and
variant sharing (mogaf.config, workflow/rules/common.smk) are derived from
this table; adding a stage is one spec here, one rule file and one module.

Paths: `output` is relative to the folder of one scene and ratio,
results/{dataset}/{scene}/ratio{r}/ (ingest's to the scene folder). The rule
file writes exactly `rule_output(name)`.
"""

from __future__ import annotations

from dataclasses import dataclass

RESULTS = "results"
RATIO_DIR = RESULTS + "/{dataset}/{scene}/ratio{ratio}/"
SCENE_DIR = RESULTS + "/{dataset}/{scene}/"


@dataclass(frozen=True)
class PathInput:
    """One input path: the CLI option (`--model-h5`) and the stage function's argument."""

    option: str
    argument: str
    required: bool = True


@dataclass(frozen=True)
class StageSpec:
    name: str  # the rule's name and the key of its artefact in mogaf.config's tables
    function: str  # entry point in mogaf.stages
    output: str | None = None  # artefact file; None: several (forecast parts, evaluate's pair)
    inputs: tuple[PathInput, ...] = ()
    output_argument: str = "out"  # the function's argument holding the output path
    settings: str | None = None  # config section passed as `params`
    # What determines the artefact besides its upstream stages: config keys
    # (dotted); None: the stage is never shared across variants by this table.
    digest_sections: tuple[str, ...] | None = None
    upstream: tuple[str, ...] = ()
    seeded: bool = False  # takes the config's `seed`
    device: bool = False  # takes the config's `device`
    checkpoint: bool = False  # takes a resumable training checkpoint
    per_scene: bool = False  # one artefact per scene (before the split), not per ratio
    cli: str | None = None  # its `python -m mogaf` subcommand, when that takes only path options


def _paths(*items: str) -> tuple[PathInput, ...]:
    """'model-h5:model' -> PathInput('model-h5', 'model'); a trailing '?' makes it optional."""
    out = []
    for item in items:
        option, argument = item.split(":")
        out.append(PathInput(option, argument.rstrip("?"), required=not argument.endswith("?")))
    return tuple(out)


STAGES: tuple[StageSpec, ...] = (
    StageSpec(
        "synthesize",
        "synthesize",
        output="source",
        output_argument="out_dir",
        per_scene=True,
        inputs=(),
        cli="synthesize",
    ),
    StageSpec("ingest", "ingest", output="scene.h5", per_scene=True, inputs=_paths("folder:folder"), cli="ingest"),
    StageSpec("split", "split", output="split.h5", inputs=_paths("scene-h5:scene"), cli="split"),
    StageSpec(
        "priors",
        "priors",
        output="priors.h5",
        inputs=_paths("scene-h5:scene", "split-h5:split"),
        settings="priors",
        digest_sections=("seed", "priors"),
        seeded=True,
        cli="priors",
    ),
    StageSpec(
        "recon",
        "recon",
        output="recon.h5",
        inputs=_paths("scene-h5:scene", "split-h5:split", "priors-h5:priors"),
        settings="recon",
        digest_sections=("seed", "device", "recon"),
        upstream=("priors",),
        seeded=True,
        device=True,
        checkpoint=True,
        cli="recon",
    ),
    StageSpec(
        "group",
        "group",
        output="groups.h5",
        inputs=_paths("model-h5:model", "priors-h5:priors", "scene-h5:scene"),
        settings="grouping",
        digest_sections=("grouping",),
        upstream=("recon", "priors"),
        seeded=True,
        cli="group",
    ),
    StageSpec(
        "rigid_init",
        "rigid_init",
        output="rigid.h5",
        inputs=_paths("model-h5:model", "groups-h5:groups"),
        settings="rigid_init",
        digest_sections=("rigid_init",),
        upstream=("group",),
        cli="rigid-init",
    ),
    StageSpec(
        "refine",
        "refine",
        output="refined.h5",
        inputs=_paths(
            "model-h5:model",
            "groups-h5:groups",
            "rigid-h5:rigid?",
            "priors-h5:priors",
            "scene-h5:scene",
            "split-h5:split",
        ),
        settings="refine",
        digest_sections=("seed", "device", "refine"),
        upstream=("recon", "group", "rigid_init"),
        seeded=True,
        device=True,
        checkpoint=True,
        cli="refine",
    ),
    StageSpec(
        "grouping_quality",
        "grouping_quality",
        output="grouping_quality.h5",
        inputs=_paths("grouped-model-h5:grouped_model", "groups-h5:groups", "scene-h5:scene", "split-h5:split"),
        settings="grouping_quality",
        digest_sections=("grouping_quality",),
        upstream=("group", "recon"),
        cli="grouping-quality",
    ),
    # one per model, so the variants forecasting from one model share it
    StageSpec(
        "reconstruction_quality:recon",
        "reconstruction_quality",
        output="reconstruction_quality/recon.h5",
        inputs=_paths("model-h5:model", "scene-h5:scene", "split-h5:split"),
        settings="reconstruction_quality",
        digest_sections=("reconstruction_quality",),
        upstream=("recon",),
        cli="reconstruction-quality",
    ),
    StageSpec(
        "reconstruction_quality:refine",
        "reconstruction_quality",
        output="reconstruction_quality/refined.h5",
        inputs=_paths("model-h5:model", "scene-h5:scene", "split-h5:split"),
        settings="reconstruction_quality",
        digest_sections=("reconstruction_quality",),
        upstream=("refine",),
    ),
    # A forecast's sections and upstream depend on the method and the config
    # (mogaf.config._sections / _upstream); one job per motion group, merged.
    StageSpec(
        "forecast_group",
        "forecast_group",
        inputs=_paths("model-h5:model", "groups-h5:groups", "split-h5:split"),
        settings="forecast",
        seeded=True,
        device=True,
        cli="forecast-group",
    ),
    StageSpec("forecast", "forecast_merge", settings="forecast", seeded=True),
    StageSpec(
        "evaluate",
        "evaluate",
        output="metrics.json",
        output_argument="out_metrics",
        settings="evaluate",
        digest_sections=("evaluate", "forecast.methods"),
    ),
    # opt-in, no stage reads it: one method's forecast as 3DGS PLY files
    # (ply/ beside index.json) for Gaussian-splatting viewers
    StageSpec(
        "export",
        "export",
        output="export/{method}/index.json",
        inputs=_paths("model-h5:model", "forecast-h5:forecast", "scene-h5:scene", "split-h5:split"),
        settings="export",
        cli="export",
    ),
)

BY_NAME: dict[str, StageSpec] = {spec.name: spec for spec in STAGES}
BY_COMMAND: dict[str, StageSpec] = {spec.cli: spec for spec in STAGES if spec.cli}


def spec(name: str) -> StageSpec:
    return BY_NAME[name]


def artefact_files() -> dict[str, str]:
    """stage -> its artefact, relative to the ratio folder (stages with one per ratio)."""
    return {s.name: s.output for s in STAGES if s.output and not s.per_scene and s.digest_sections is not None}


def digest_sections() -> dict[str, tuple[str, ...]]:
    return {s.name: s.digest_sections for s in STAGES if s.digest_sections is not None}


def upstream() -> dict[str, tuple[str, ...]]:
    """Fixed upstream stages (forecast and evaluate follow the config: mogaf.config)."""
    return {s.name: s.upstream for s in STAGES if s.digest_sections is not None and s.name != "evaluate"}


def rule_output(name: str) -> str:
    """The path pattern the stage's rule writes (Snakemake wildcards)."""
    s = BY_NAME[name]
    if s.output is None:
        raise KeyError(f"stage {name} has no single artefact")
    if s.per_scene:
        return SCENE_DIR + s.output
    # the split is made once per ratio and shared by every variant
    return RATIO_DIR + ("" if name == "split" else "{prefix}") + s.output
