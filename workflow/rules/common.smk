"""Shared setup: config validation, wildcards, artefact paths and input functions."""

import functools
import os
from pathlib import Path

from snakemake.exceptions import WorkflowError
from snakemake.logging import logger

import mogaf.config as mcfg
import mogaf.paths as mpaths
import mogaf.registry as mreg
from mogaf.errors import MogafError
from mogaf.forecast.params import load_mogaf
from mogaf.schema import config_error, file_layers, load_config_schema, setting_source

SCHEMA = Path(workflow.basedir) / "config" / "schema.yaml"
ABLATION_SCHEMA = Path(workflow.basedir) / "config" / "ablations.schema.yaml"


def _config_layers():
    """The config as Snakemake merged it, lowest precedence first: the
    Snakefile's configfile, the --configfile files in order, --config."""
    given = [str(f) for f in (workflow.config_settings.configfiles or [])]
    files = [str(f) for f in workflow.configfiles if str(f) not in given] + given
    # one file given twice (the Snakefile's config/config.yaml and --configfile
    # config/config.yaml, in two spellings) is one layer, at its last place
    real = [os.path.realpath(f) for f in files]
    files = [f for i, f in enumerate(files) if real[i] not in real[i + 1 :]]
    layers = file_layers(files)
    if workflow.config_settings.config:
        layers.append(("--config", workflow.config_settings.config))
    return layers


def _validate(cfg, schema, layers):
    """The schema check as one line naming the config file and the key
    (Snakemake's own `validate` prints the schema it failed, a page of it)."""
    try:
        error = config_error(cfg, load_config_schema(schema), layers)
    except MogafError as exc:
        raise WorkflowError(str(exc))
    if error is not None:
        raise WorkflowError(str(error))


_validate(config, SCHEMA, _config_layers())
# config/config.yaml holds only what a user changes: every other stage setting
# takes its default from the stage's settings dataclass (mogaf.settings).
config.update(mcfg.with_defaults(config))


def _check_relations(cfg, where=""):
    """Relations between settings the schema cannot express, refused before
    any job runs (of the config and of every ablation variant)."""
    try:
        load_mogaf(cfg["forecast"]["mogaf"])
    except MogafError as exc:
        raise WorkflowError(f"{where}{exc}")


_check_relations(config)

# Every pipeline write goes to results/ or the cache folder (kernels, LPIPS).
# results/ inside a dataset (a link into one) is refused before any job creates
# its log and benchmark folders there.
try:
    mpaths.check_results_folder(
        "results",
        [
            mcfg.scene_dir(config, dataset, scene)
            for dataset, spec in config["datasets"].items()
            for scene in spec.get("scenes") or []
        ],
    )
except MogafError as exc:
    raise WorkflowError(str(exc))
mpaths.use_cache_dir(config["cache_dir"])


def _ablations_path():
    """config's ablations_file, relative to the working directory, else to the repository."""
    path = Path(config["ablations_file"])
    if not path.is_absolute() and not path.exists():
        path = Path(workflow.basedir) / path
    return path


def _load_ablations():
    path = _ablations_path()
    try:
        data = mcfg.load_yaml(path)
    except MogafError as exc:
        raise WorkflowError(str(exc))
    _validate(data, ABLATION_SCHEMA, [(str(path), data)])
    for name in data.get("variants", {}):
        try:
            mcfg.check_variant_name(name)
        except MogafError as exc:
            raise WorkflowError(str(exc))
        # A variant's merged config must satisfy the same schema.
        overrides = data["variants"][name].get("overrides") or {}
        variant = mcfg.variant_config(config, data["variants"], name)
        _validate(variant, SCHEMA, _config_layers() + [(f"{path}: variant '{name}'", overrides)])
        _check_relations(variant, f"{path}: variant '{name}': ")
    return data


ABLATIONS = _load_ablations()
VARIANTS = ABLATIONS.get("variants", {})


# A forecaster value that the other settings leave without effect is a
# warning, not an error (a sweep's variants switch the setting that silences
# it): the config's own, naming the file that sets it, now; a variant's own,
# when the variant is asked for (scene_cfg).
_WARNED = set()


def _warn_once(line):
    if line not in _WARNED:
        _WARNED.add(line)
        logger.warning(line)


_BASE_INERT, _VARIANT_INERT = mcfg.inert_forecaster_settings(config, VARIANTS)
for _key, _line in _BASE_INERT:
    _warn_once(f"{setting_source(['forecast', 'mogaf', *_key.split('.')], _config_layers())}: {_line}")


onstart:
    # A job writing into a read-only folder fails inside Snakemake (removing
    # old outputs, creating the log) with its traceback: say it once, first.
    for job in workflow.dag.needrun_jobs():
        for path in [*job.output, *job.log]:
            found = mpaths.unwritable_folder(path)
            if found is not None:
                raise WorkflowError(
                    f"{found[0]}: not writable ({found[1]}); rule {job.rule.name} writes {path} there"
                )


wildcard_constraints:
    dataset=r"[A-Za-z0-9_.-]+",
    scene=r"[A-Za-z0-9_.-]+",
    # Any text: the split stage rejects ratios outside (0, 1) with one line.
    ratio=r"[^/]+",
    prefix=r"(ablation/[A-Za-z0-9_.-]+/)?",
    method="|".join(mcfg.FORECAST_METHODS),
    group=r"all|[0-9]+",
    model=r"recon|refined",


def _workflow_error(fn):
    """Report MogafError from input functions as a one-line WorkflowError."""

    @functools.wraps(fn)  # Snakemake reads the signature to pass arguments
    def wrapped(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except MogafError as exc:
            raise WorkflowError(str(exc))

    return wrapped


# ------------------------------------------------------------------ configs
def variant_of(wildcards):
    prefix = getattr(wildcards, "prefix", "")
    return prefix.split("/")[1] if prefix else None


@_workflow_error
def scene_cfg(wildcards, variant=None):
    """Config for this dataset/scene (and variant), overrides applied."""
    variant = variant if variant is not None else variant_of(wildcards)
    for _, line in _VARIANT_INERT.get(variant, ()):
        _warn_once(f"{_ablations_path()}: variant '{variant}': {line}")
    merged = mcfg.variant_config(config, VARIANTS, variant)
    return mcfg.scene_config(merged, wildcards.dataset, wildcards.scene)


def base_cfg(wildcards):
    return scene_cfg(wildcards, variant="")


def stage_prefix(stage, wildcards):
    """Where this variant's artefact of `stage` lives ('' = shared)."""
    variant = variant_of(wildcards)
    return mcfg.artefact_prefix(stage, base_cfg(wildcards), scene_cfg(wildcards), variant)


def ratio_path(wildcards, name):
    return f"{mcfg.ratio_dir(wildcards.dataset, wildcards.scene, wildcards.ratio)}/{name}"


def stage_path(stage, wildcards):
    return ratio_path(wildcards, f"{stage_prefix(stage, wildcards)}{mcfg.ARTEFACT_FILES[stage]}")


def artefact(stage):
    """The path pattern of a stage's artefact (mogaf.registry), for its rule's output."""
    return mreg.rule_output(stage)


def scene_h5(wildcards):
    return mreg.rule_output("ingest").format(dataset=wildcards.dataset, scene=wildcards.scene)


def split_h5(wildcards):
    return ratio_path(wildcards, mreg.spec("split").output)


def params_for(section):
    """Rule params: one config section for this scene/variant."""
    return lambda wildcards: scene_cfg(wildcards)[section]


def seed(wildcards):
    return scene_cfg(wildcards)["seed"]


def device(wildcards):
    return scene_cfg(wildcards)["device"]


def benchmark_tsv(stage):
    return f"results/{{dataset}}/{{scene}}/ratio{{ratio}}/{{prefix}}benchmarks/{stage}.tsv"


def log_file(stage):
    return f"results/{{dataset}}/{{scene}}/ratio{{ratio}}/{{prefix}}logs/{stage}.log"


# ------------------------------------------------------------------ datasets
@_workflow_error
def dataset_folder(wildcards):
    """The scene's folder; a missing folder fails the DAG with one line."""
    layout = mcfg.dataset_layout(config, wildcards.dataset)
    folder = mcfg.scene_dir(config, wildcards.dataset, wildcards.scene)
    if layout == "synthetic" or Path(folder).is_dir():
        return folder
    from mogaf.datasets import describe_missing

    raise MogafError(describe_missing(layout, Path(folder), wildcards.dataset, wildcards.scene))


def synthetic_datasets():
    return [name for name, ds in config["datasets"].items() if ds["layout"] == "synthetic"] or ["none"]


# ------------------------------------------------------------------ targets
def _ratio_str(value):
    return f"{float(value):g}"


def _sweep_variants(name):
    sweeps = ABLATIONS.get("sweeps", {})
    if name not in sweeps:
        raise WorkflowError(f"unknown sweep '{name}' (config/ablations.yaml sweeps: {', '.join(sweeps)})")
    return sweeps[name]["variants"]


def scope_targets(scope, sweeps=()):
    """metrics.json of a {dataset, scenes, ratios} scope, plus its sweeps' variants."""
    out = []
    for scene in scope["scenes"]:
        for ratio in scope["ratios"]:
            base = mcfg.ratio_dir(scope["dataset"], scene, _ratio_str(ratio))
            out.append(f"{base}/metrics.json")
            for name in sweeps:
                out += [f"{base}/ablation/{v}/metrics.json" for v in _sweep_variants(name)]
    return out


def grid_targets():
    out = []
    for entry in config["grid"]:
        out += scope_targets(entry, entry.get("sweeps", []))
    return out


def sweep_targets(name):
    demo = config["demo"]
    scopes = ABLATIONS["sweeps"].get(name, {}).get("targets") or [
        {"dataset": demo["dataset"], "scenes": [demo["scene"]], "ratios": [demo["ratio"]]}
    ]
    return [t for scope in scopes for t in scope_targets(scope, [name])]


def demo_targets():
    demo = config["demo"]
    base = mcfg.ratio_dir(demo["dataset"], demo["scene"], _ratio_str(demo["ratio"]))
    out = [
        f"{base}/metrics.json",
        f"{base}/report/videos",
        f"{base}/report/quality.png",
        "results/tables/table_forecast.md",
        "results/tables/table_forecast.html",
        "results/tables/error_vs_runtime.png",
    ]
    for name in demo.get("sweeps", []):
        out += sweep_targets(name)
    return out


# ------------------------------------------------------------------ groups (checkpoint)
def groups_h5(wildcards):
    """groups.h5 of this variant, after the checkpoint has run."""
    prefix = stage_prefix("group", wildcards)
    return checkpoints.group.get(
        dataset=wildcards.dataset, scene=wildcards.scene, ratio=wildcards.ratio, prefix=prefix
    ).output[0]


def refine_inputs(wildcards):
    inputs = {
        "model": stage_path("recon", wildcards),
        "groups": groups_h5(wildcards),
        "priors": stage_path("priors", wildcards),
        "scene": scene_h5(wildcards),
        "split": split_h5(wildcards),
    }
    from mogaf.grouping.stage import has_rigid_groups

    if has_rigid_groups(inputs["groups"]):
        inputs["rigid"] = stage_path("rigid_init", wildcards)
    return inputs


# ------------------------------------------------------------------ forecasts
def forecast_prefix(wildcards):
    return stage_prefix(f"forecast:{wildcards.method}", wildcards)


def forecast_model(wildcards):
    """refined.h5, or recon.h5 for the ablation without group-wise optimisation."""
    return stage_path(mcfg.forecast_input_stage(scene_cfg(wildcards)), wildcards)


def quality_model(wildcards):
    """recon.h5 or refined.h5, by the {model} wildcard of reconstruction_quality."""
    return stage_path({"recon": "recon", "refined": "refine"}[wildcards.model], wildcards)


def forecast_params(wildcards):
    """Only what one method's forecast depends on (other methods' settings
    must not trigger a rerun)."""
    from mogaf.forecast import param_section, section_params

    fc = scene_cfg(wildcards)["forecast"]
    section = param_section(wildcards.method)
    out = {key: fc[key] for key in ("input", "groupwise", "common")}
    out[section] = section_params(wildcards.method, fc[section])
    return out


def forecast_part_files(wildcards):
    from mogaf.forecast.stage import forecast_jobs, method_jobs

    cfg = scene_cfg(wildcards)
    jobs = method_jobs(wildcards.method, forecast_jobs(groups_h5(wildcards), groupwise=cfg["forecast"]["groupwise"]))
    base = ratio_path(wildcards, forecast_prefix(wildcards))
    return [f"{base}forecast/{wildcards.method}/group{job}.h5" for job in jobs]


# ------------------------------------------------------------------ evaluation and reports
def forecast_h5(wildcards, method):
    prefix = stage_prefix(f"forecast:{method}", wildcards)
    return ratio_path(wildcards, f"{prefix}forecast/{method}.h5")


def _benchmarks_of(wildcards):
    """Benchmark TSVs of every stage in this result's lineage."""
    cfg = scene_cfg(wildcards)
    out = {"bench_ingest": f"results/{wildcards.dataset}/{wildcards.scene}/benchmarks/ingest.tsv"}
    stages = ["priors", "recon", "group"]
    model_stage = mcfg.forecast_input_stage(cfg)
    if model_stage == "refine":
        stages.append("refine")
        from mogaf.grouping.stage import has_rigid_groups

        if has_rigid_groups(groups_h5(wildcards)):
            stages.append("rigid_init")
    for stage in stages:
        out[f"bench_{stage}"] = ratio_path(wildcards, f"{stage_prefix(stage, wildcards)}benchmarks/{stage}.tsv")
    from mogaf.forecast.stage import forecast_jobs, method_jobs

    jobs = forecast_jobs(groups_h5(wildcards), groupwise=cfg["forecast"]["groupwise"])
    for method in cfg["forecast"]["methods"]:
        base = ratio_path(wildcards, stage_prefix(f"forecast:{method}", wildcards))
        out[f"bench_forecast_{method}"] = f"{base}benchmarks/forecast_{method}.tsv"
        for job in method_jobs(method, jobs):
            out[f"bench_forecast_{method}_group{job}"] = f"{base}benchmarks/forecast_{method}_group{job}.tsv"
    return out


def evaluate_inputs(wildcards):
    cfg = scene_cfg(wildcards)
    inputs = {
        "scene": scene_h5(wildcards),
        "split": split_h5(wildcards),
        "model": forecast_model(wildcards),
        "groups": groups_h5(wildcards),  # its lineage only (mogaf.stages.evaluate)
        "reconstruction_quality": stage_path(mcfg.reconstruction_quality_stage(cfg), wildcards),
        "grouping_quality": stage_path("grouping_quality", wildcards),
    }
    for method in cfg["forecast"]["methods"]:
        inputs[f"forecast_{method}"] = forecast_h5(wildcards, method)
    inputs.update(_benchmarks_of(wildcards))
    return inputs


def scene_report_inputs(wildcards):
    cfg = scene_cfg(wildcards)
    return {
        "metrics": ratio_path(wildcards, f"{wildcards.prefix}metrics.json"),
        "renders": ratio_path(wildcards, f"{wildcards.prefix}renders"),
        "grouping_quality": stage_path("grouping_quality", wildcards),
        "reconstruction_quality": stage_path(mcfg.reconstruction_quality_stage(cfg), wildcards),
    }


def configured_metrics(wildcards=None):
    """The metrics.json files this config builds: its grid's and its demo's."""
    return sorted(set(demo_targets_metrics()) | set(grid_targets()))


def other_metrics():
    """metrics.json files under results/ that this config does not build
    (another config's runs). The tables read them as plain files: as inputs
    they would join the DAG, and `-R evaluate` under this config would rerun
    them without their config, fail and delete them."""
    found = {str(p) for p in Path("results").glob("**/metrics.json")}
    return sorted(found - set(configured_metrics()))


def demo_targets_metrics():
    return [t for t in demo_targets() if t.endswith("metrics.json")]


def runtime_report_params():
    sweep = ABLATIONS.get("sweeps", {}).get(config["report"]["runtime_sweep"], {})
    return {**config["report"], "runtime_variants": list(sweep.get("variants", []))}
