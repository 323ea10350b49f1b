"""Shared setup: config validation, wildcards, artefact paths and input functions."""

import functools
import os
import string
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


@functools.cache
def _config_layers():
    """The config as Snakemake merged it, lowest precedence first: the
    Snakefile's configfile, the --configfile files in order, --config.
    Read once: every ablation variant's check names them."""
    given = [str(f) for f in (workflow.config_settings.configfiles or [])]
    files = [str(f) for f in workflow.configfiles if str(f) not in given] + given
    # one file given twice (the Snakefile's config/config.yaml and --configfile
    # config/config.yaml, in two spellings) is one layer, at its last place
    real = [os.path.realpath(f) for f in files]
    files = [f for i, f in enumerate(files) if real[i] not in real[i + 1 :]]
    layers = file_layers(files)
    if workflow.config_settings.config:
        layers.append(("--config", workflow.config_settings.config))
    return tuple(layers)


@functools.cache
def _schema(path):
    """A schema file, read (and its stage sections generated) once per workflow."""
    return load_config_schema(path)


def _validate(cfg, schema, layers):
    """The schema check as one line naming the config file and the key
    (Snakemake's own `validate` prints the schema it failed, a page of it)."""
    try:
        error = config_error(cfg, _schema(schema), layers)
    except MogafError as exc:
        raise WorkflowError(str(exc))
    if error is not None:
        raise WorkflowError(str(error))


_validate(config, SCHEMA, list(_config_layers()))
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
    return mcfg.ablations_path(config, workflow.basedir)


def _load_ablations():
    path = _ablations_path()
    try:
        data = mcfg.load_yaml(path)
    except MogafError as exc:
        raise WorkflowError(str(exc))
    _validate(data, ABLATION_SCHEMA, [(str(path), data)])
    for name in data.get("variants", {}):
        overrides = data["variants"][name].get("overrides") or {}
        try:
            mcfg.check_variant(path, name, overrides)
        except MogafError as exc:
            raise WorkflowError(str(exc))
        # A variant's merged config must satisfy the same schema.
        variant = mcfg.variant_config(config, data["variants"], name)
        _validate(variant, SCHEMA, [*_config_layers(), (f"{path}: variant '{name}'", overrides)])
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
    if variant:
        overrides = VARIANTS.get(variant, {}).get("overrides") or {}
        for key in mcfg.variant_keys_set_for_scene(config, overrides, wildcards.dataset, wildcards.scene):
            _warn_once(
                f"{_ablations_path()}: variant '{variant}': {key} does not change {wildcards.dataset}/"
                f"{wildcards.scene}: the dataset's overrides or scene_overrides set it, and they win"
            )
    merged = mcfg.variant_config(config, VARIANTS, variant)
    return mcfg.scene_config(merged, wildcards.dataset, wildcards.scene)


def base_cfg(wildcards):
    return scene_cfg(wildcards, variant="")


def stage_prefix(stage, wildcards):
    """Where this variant's artefact of `stage` lives ('' = shared)."""
    variant = variant_of(wildcards)
    return mcfg.artefact_prefix(stage, base_cfg(wildcards), scene_cfg(wildcards), variant)


def params_for(section):
    """Rule params: one config section for this scene/variant."""
    return lambda wildcards: scene_cfg(wildcards)[section]


def seed(wildcards):
    return scene_cfg(wildcards)["seed"]


def device(wildcards):
    return scene_cfg(wildcards)["device"]


# ------------------------------------------------------------------ scheduling
# With more jobs ready than cores, Snakemake starts the higher priority first:
# the chain every forecast waits for, then the trained forecasts (the longest
# jobs: started late, they trail alone at the end), then the jobs only
# evaluation reads. Rules not listed: 0. Among the forecast jobs of one rule,
# forecast.start_first's methods go first, in its order (forecast_priority).
PRIORITY = {
    **dict.fromkeys(["synthesize", "ingest", "split", "priors", "recon", "group", "rigid_init", "refine"], 3),
    "forecast_group": 2,
    **dict.fromkeys(["forecast", "grouping_quality", "reconstruction_quality"], 1),
}


def forecast_priority(rule):
    """The priority of a forecast rule's job: PRIORITY[rule], raised below the
    next integer by its method's place in forecast.start_first."""
    from mogaf.forecast.params import job_priority

    def priority(wildcards):
        start_first = scene_cfg(wildcards)["forecast"].get("start_first", [])
        return job_priority(PRIORITY[rule], wildcards.method, start_first)

    return priority


# ------------------------------------------------------------------ paths (patterns: mogaf.registry)
def artefact(stage, role=None):
    """The path pattern of a stage's artefact (or further output `role`), for its rule's output."""
    return mreg.rule_output(stage, role)


def log_file(name, scope=None):
    """The log of a rule's job: results/.../{prefix}logs/<job>.log (mogaf.registry.job_path)."""
    return mreg.job_path("log", name, scope)


def benchmark_tsv(name):
    return mreg.job_path("benchmark", name)


def _fill(pattern, wildcards, prefix, **extra):
    return pattern.format(**{**dict(wildcards.items()), "prefix": prefix, **extra})


def _variant_prefix(stage, wildcards, **extra):
    """'' or ablation/<variant>/: where this variant's artefact of `stage` lives."""
    spec = mreg.spec(stage)
    if spec.scope != "variant":
        return ""
    key = (spec.variant_key or spec.name).format(**{**dict(wildcards.items()), **extra})
    return stage_prefix(key, wildcards)


def artefact_path(stage, wildcards, **extra):
    """This variant's artefact of `stage` (a spec name), for these wildcards."""
    return _fill(mreg.rule_output(stage), wildcards, _variant_prefix(stage, wildcards, **extra), **extra)


def job_file(kind, stage, wildcards, **extra):
    """This variant's log, benchmark or checkpoint of a job of `stage`."""
    return _fill(mreg.job_path(kind, stage), wildcards, _variant_prefix(stage, wildcards, **extra), **extra)


@_workflow_error
def checkpoint_output(stage, wildcards):
    """This variant's artefact of checkpoint rule `stage`, once it has run.

    The scene is checked first: for a scene the config does not list but
    whose checkpoint artefact is on disk (made under another config),
    Snakemake takes the checkpoint for not yet run and would start the job
    with its inputs unresolved, a traceback instead of the one-line error."""
    mcfg.check_scene(config, wildcards.dataset, wildcards.scene)
    values = {**dict(wildcards.items()), "prefix": _variant_prefix(stage, wildcards)}
    names = [name for _, name, _, _ in string.Formatter().parse(mreg.rule_output(stage)) if name]
    return getattr(checkpoints, mreg.spec(stage).rule).get(**{name: values[name] for name in names}).output[0]


def _source(item, wildcards):
    """The stage whose artefact the input `item` (mogaf.registry.Input) is."""
    return item.source if isinstance(item.source, str) else item.source(scene_cfg(wildcards), wildcards)


def resolved_inputs(stage, wildcards):
    """argument -> (source stage, path) of the inputs the registry gives `stage`
    (its rule file gives those without a source)."""
    out = {}
    for item in mreg.spec(stage).inputs:
        if item.source is None:
            continue
        source = _source(item, wildcards)
        path = checkpoint_output(source, wildcards) if item.checkpoint else artefact_path(source, wildcards)
        if item.only_if is not None:
            predicate, argument = item.only_if
            if not mreg.load(predicate)(out[argument][1]):
                continue
        out[item.argument] = (source, path)
    return out


def stage_inputs(stage):
    """The input function of a stage's rule: `input: unpack(stage_inputs("refine"))`."""

    @_workflow_error
    def inputs(wildcards):
        return {argument: path for argument, (_, path) in resolved_inputs(stage, wildcards).items()}

    inputs.__name__ = f"{mreg.spec(stage).rule}_inputs"
    return inputs


def stage_params(stage):
    """The params of a stage's rule, `params: **stage_params("refine")` (its config
    section, seed, device and training checkpoint, as its spec takes them)."""
    spec = mreg.spec(stage)
    out = {}
    if spec.settings is not None:
        out[spec.settings] = params_for(spec.settings)
    if spec.seeded:
        out["seed"] = seed
    if spec.uses_device:
        out["device"] = device
    if spec.checkpoint:
        # survives a killed job so that a rerun resumes instead of starting over
        out["checkpoint"] = mreg.job_path("checkpoint", stage)
    return out


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


# ------------------------------------------------------------------ forecasts
def forecast_params(wildcards):
    """Only what one method's forecast depends on (other methods' settings
    must not trigger a rerun)."""
    from mogaf.forecast.params import param_section, section_params

    fc = scene_cfg(wildcards)["forecast"]
    section = param_section(wildcards.method)
    out = {key: fc[key] for key in ("input", "groupwise", "common")}
    out[section] = section_params(wildcards.method, fc[section])
    return out


def forecast_merge_params(wildcards):
    """forecast_params; for a merge job that trains (_merge_trains) also the
    layout and the device (under per_group the params stay what they were:
    nothing reruns)."""
    out = forecast_params(wildcards)
    if _merge_trains(wildcards):
        out.update(jobs="per_method", device=device(wildcards))
    return out


def _forecast_layout(wildcards):
    from mogaf.forecast.stage import job_layout

    return job_layout(scene_cfg(wildcards)["forecast"])


def _merge_trains(wildcards):
    """Whether the method's merge job trains its groups (forecast.jobs: per_method, a trained method)."""
    from mogaf.forecast.params import TRAINED_METHODS
    from mogaf.forecast.stage import merge_computes

    return wildcards.method in TRAINED_METHODS and merge_computes(wildcards.method, _forecast_layout(wildcards))


def forecast_merge_gpus(wildcards):
    """A GPU for a merge job that trains (per_method, a trained method, device cuda)."""
    return 1 if _merge_trains(wildcards) and device(wildcards) == "cuda" else 0


def forecast_merge_mem_mb(wildcards, attempt):
    """A merge job's memory: a group job's where it trains (demo: <= 3.4 GB, the
    latent ODE), else a merge's (demo: 0.4 GB); doubled on each retry."""
    return (10000 if _merge_trains(wildcards) else 1500) * 2 ** (attempt - 1)


def forecast_merge_runtime(wildcards, attempt):
    """A merge job's minutes: every group in turn where it trains (demo: <= 107 s)."""
    return (30 if _merge_trains(wildcards) else 10) * 2 ** (attempt - 1)


def _forecast_jobs(wildcards, method):
    from mogaf.forecast.stage import forecast_jobs, method_jobs

    groupwise = scene_cfg(wildcards)["forecast"]["groupwise"]
    jobs = forecast_jobs(checkpoint_output("group", wildcards), groupwise=groupwise)
    return method_jobs(method, jobs, _forecast_layout(wildcards))


def forecast_part_files(wildcards):
    return [
        artefact_path("forecast_group", wildcards, group=job) for job in _forecast_jobs(wildcards, wildcards.method)
    ]


# ------------------------------------------------------------------ evaluation and reports
def _lineage(stage, wildcards, seen):
    """The stages `stage`'s inputs come from, transitively, as the rules resolve them."""
    for source, _ in resolved_inputs(stage, wildcards).values():
        if source not in seen:
            seen.append(source)
            _lineage(source, wildcards, seen)
    return seen


def _benchmarks_of(wildcards):
    """Benchmark TSVs of every stage in this result's lineage (the stages whose
    spec counts its run time) and of every method's forecast jobs."""
    out = {}
    for stage in _lineage("forecast_group", wildcards, []):
        if mreg.spec(stage).runtime:
            out[f"bench_{mreg.job_name(stage)}"] = job_file("benchmark", stage, wildcards)
    for method in scene_cfg(wildcards)["forecast"]["methods"]:
        out[f"bench_forecast_{method}"] = job_file("benchmark", "forecast", wildcards, method=method)
        for job in _forecast_jobs(wildcards, method):
            path = job_file("benchmark", "forecast_group", wildcards, method=method, group=job)
            out[f"bench_forecast_{method}_group{job}"] = path
    return out


def evaluate_inputs(wildcards):
    cfg = scene_cfg(wildcards)
    inputs = {
        "scene": artefact_path("ingest", wildcards),
        "split": artefact_path("split", wildcards),
        "model": artefact_path(mcfg.forecast_input_stage(cfg), wildcards),
        "groups": checkpoint_output("group", wildcards),  # its lineage only (mogaf.stages.evaluate)
        "reconstruction_quality": artefact_path(mcfg.reconstruction_quality_stage(cfg), wildcards),
        "grouping_quality": artefact_path("grouping_quality", wildcards),
    }
    for method in cfg["forecast"]["methods"]:
        inputs[f"forecast_{method}"] = artefact_path("forecast", wildcards, method=method)
    inputs.update(_benchmarks_of(wildcards))
    return inputs


def scene_report_inputs(wildcards):
    cfg = scene_cfg(wildcards)
    return {
        # this result's own (the target's prefix), not a shared one
        "metrics": _fill(mreg.rule_output("evaluate"), wildcards, wildcards.prefix),
        "renders": _fill(mreg.rule_output("evaluate", "renders"), wildcards, wildcards.prefix),
        "grouping_quality": artefact_path("grouping_quality", wildcards),
        "reconstruction_quality": artefact_path(mcfg.reconstruction_quality_stage(cfg), wildcards),
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
