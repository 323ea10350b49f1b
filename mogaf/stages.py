"""Stage entry points: explicit paths in, artefact out.

Every stage is described once, by its StageSpec in mogaf.registry. The
generic runner `run(name, **arguments)` runs any stage from its spec:

1. it refuses, before it opens anything for writing, an output that would
   overwrite or delete one of its inputs or write into a dataset folder
   (`mogaf.paths.check_outputs`);
2. it runs the spec's guards (`before_inputs` first);
3. it declares the artefacts the stage reads (`mogaf.artefact.stage_inputs`):
   they must share one lineage, and what it writes records them;
4. it calls the spec's library function, imported only now (torch loads
   only when a stage that needs it runs).

`mogaf.stages.<stage>(...)` is that runner with the stage's arguments
(inputs in the spec's order, the output, params, then the rest);
`run_rule(snakemake)` is the one Snakemake script's entry
(workflow/scripts/run_stage.py) and the CLI (`python -m mogaf`) calls the
same entries. A bad input raises MogafError, which `run_stage` turns into
one line and exit status 1.

Stages whose shape the generic runner does not fit keep a dedicated wrapper
here (the spec's `wrapper`): synthesize (replaces a whole folder, settings
per scene name), ingest (reads a dataset folder, not an artefact),
forecast_group and forecast_merge (call mogaf.forecast.stage, refactored on
its own), evaluate (a dynamic set of forecasts and benchmarks) and the
report entries (scene_report, tables, runtime_report).
"""

from __future__ import annotations

import inspect
import logging
import numbers
import os
import sys
import time
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from . import registry
from .allocator import keep_heap
from .artefact import atomic_path, check_made_from, config_digest, open_artefact, stage_inputs, write_error
from .cores import fixed_cores
from .errors import MogafError, input_error
from .paths import check_outputs

log = logging.getLogger("mogaf")


# ------------------------------------------------------------------ running
def process_cpu_s() -> float:
    """CPU seconds (user + system, every thread) this process has used since it started."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_SELF)
    return float(usage.ru_utime + usage.ru_stime)


def _setup_logging(log_path: str | os.PathLike | None) -> None:
    root = logging.getLogger()
    root.setLevel(logging.INFO)
    for handler in list(root.handlers):
        root.removeHandler(handler)
    fmt = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s")
    if log_path:
        try:
            Path(log_path).parent.mkdir(parents=True, exist_ok=True)
            handler: logging.Handler = logging.FileHandler(log_path, mode="w")
        except OSError as exc:  # a read-only or full results folder
            raise write_error(log_path, exc) from None
    else:
        handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(fmt)
    root.addHandler(handler)


def set_threads(threads: int | None, *, torch_threads: bool = True) -> None:
    """Torch's thread count; None leaves torch's default, and so does a stage
    that sets none (torch_threads False: registry.StageSpec), which neither
    imports torch for it nor takes a bad count."""
    if threads is None:
        return
    if isinstance(threads, bool) or not isinstance(threads, numbers.Integral) or threads < 1:
        raise MogafError(f"threads must be a positive integer, got {threads!r}")
    if not torch_threads:
        return
    import torch

    torch.set_num_threads(int(threads))


def _warning_to_log(log_path: str | os.PathLike | None) -> Callable[..., None]:
    """A `warnings.showwarning` that logs a warning as one line (and, when the
    log goes to a file, also prints it, so that Snakemake's console shows it).
    mogaf's own warnings (UserWarning) name their file already; any other
    says what raised it and where."""

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        text = " ".join(str(message).split())
        if not issubclass(category, UserWarning):
            text = f"{category.__name__}: {text} ({filename}:{lineno})"
        log.warning("%s", text)
        if log_path:
            print(f"mogaf: warning: {text}", file=sys.stderr, flush=True)

    return show


def run_stage(
    fn: Callable[..., Any],
    log_path: str | os.PathLike | None = None,
    *,
    threads: int | None = None,
    torch_threads: bool = True,
    **kwargs: Any,
) -> Any:
    """Run one stage; a MogafError becomes one line on stderr and exit 1,
    a warning one line in the log."""
    start = time.perf_counter()
    logging_ready = False
    try:
        _setup_logging(log_path)
        logging_ready = True
        keep_heap()
        fixed_cores()  # a bad MOGAF_CORES fails every stage at its start, not only those that read it
        set_threads(threads, torch_threads=torch_threads)
        with warnings.catch_warnings():
            warnings.showwarning = _warning_to_log(log_path)
            result = fn(**kwargs)
    except MogafError as exc:
        if log_path and logging_ready:
            log.error("%s", exc)
        print(f"mogaf: error: {exc}", file=sys.stderr, flush=True)
        sys.exit(1)
    except Exception:
        # An unexpected failure keeps its traceback on stderr and in the log.
        if log_path and logging_ready:
            log.exception("%s failed", fn.__name__)
        raise
    log.info("%s finished in %.1f s, process CPU %.1f s", fn.__name__, time.perf_counter() - start, process_cpu_s())
    return result


def _digest(stage: str, params: Any, **extra: Any) -> str:
    return config_digest({"stage": stage, "params": params, **extra})


def _rows(path: str | os.PathLike, key: str) -> int | None:
    """Length of entry `key` of an artefact, without reading it (None: absent)."""
    with open_artefact(path) as fh:
        return int(fh[key].shape[0]) if key in fh and fh[key].shape else None


def _check_synthetic_target(out_dir: str) -> None:
    """synthesize replaces its folder whole: only a synthetic scene or an empty
    folder may be replaced, never a folder of other files."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise input_error(out, "exists and is not a folder; synthesize writes a scene folder here")
    if out.is_dir() and any(out.iterdir()) and not (out / "splits" / "train.json").is_file():
        raise input_error(
            out,
            "exists and is not a synthetic scene; synthesize replaces its output folder, "
            "so it would delete these files: give a new or empty folder",
        )


# ------------------------------------------------------------------ the generic runner
def run(name: str, /, **arguments: Any) -> Any:
    """Run stage `name` (mogaf.registry) on explicit paths: `arguments` are
    its inputs by argument name, its output(s), `params` (with `settings`),
    its wildcards, `seed` / `device` / `checkpoint` as the spec takes them."""
    spec = registry.spec(name)
    if not spec.generic:
        raise TypeError(f"stage {spec.name} has a dedicated entry point: mogaf.stages.{spec.wrapper}")
    arguments = dict(arguments)
    paths = _input_paths(spec, arguments)
    outputs = _output_paths(spec, arguments)
    check_outputs(outputs, paths, directories=[o.role for o in spec.outputs if o.directory])
    _guards(spec, arguments, before_inputs=True)
    with stage_inputs(*paths):
        _guards(spec, arguments, before_inputs=False)
        return _call(spec, arguments)


def _input_paths(spec: registry.StageSpec, arguments: dict[str, Any]) -> list[str | None]:
    paths: list[str | None] = []
    for i in spec.inputs:
        value = arguments.get(i.argument)
        if value is None and i.required:
            raise MogafError(f"stage {spec.name}: no {i.argument} given (--{i.cli_option})")
        paths += list(value or []) if i.many else [value]
    return paths


def _output_paths(spec: registry.StageSpec, arguments: dict[str, Any]) -> dict[str, Any]:
    """role -> path; a further output left out goes beside the artefact."""
    out = arguments.get(spec.output_argument)
    if out is None:
        raise MogafError(f"stage {spec.name}: no output path given")
    outputs: dict[str, Any] = {"out": out}
    if spec.checkpoint:
        outputs["checkpoint"] = arguments.get("checkpoint")
    for o in spec.outputs:
        if arguments.get(o.argument) is None:
            arguments[o.argument] = registry.sibling(os.fspath(out), o.sibling)
        outputs[o.role] = arguments[o.argument]
    return outputs


def _guards(spec: registry.StageSpec, arguments: Mapping[str, Any], *, before_inputs: bool) -> None:
    for guard in spec.guards:
        if guard.before_inputs == before_inputs:
            registry.load(guard.check)(*(arguments.get(a) for a in guard.arguments))


def _call(spec: registry.StageSpec, arguments: Mapping[str, Any]) -> Any:
    """function(*inputs, out, params, **keywords): the spec's calling convention."""
    positional: list[Any] = [arguments.get(i.argument) for i in spec.inputs]
    positional.append(arguments[spec.output_argument])
    keywords: dict[str, Any] = {w: arguments[w] for w in spec.wildcards}
    params: dict[str, Any] | None = dict(arguments["params"] or {}) if spec.settings else None
    for key, where in (("seed", spec.seed), ("device", spec.device)):
        if where == "params" and params is not None:
            params[key] = arguments[key]
        elif where is not None:
            keywords[key] = arguments[key]
    if params is not None:
        positional.append(params)
    if spec.checkpoint:
        keywords["checkpoint"] = arguments.get("checkpoint")
    keywords.update({o.argument: arguments[o.argument] for o in spec.outputs})
    keywords.update(dict(spec.fixed))
    return registry.load(spec.function)(*positional, **keywords)


def signature(spec: registry.StageSpec) -> inspect.Signature:
    """The arguments of `mogaf.stages.<stage>`: the inputs in the spec's order,
    the output, params, wildcards, seed, device, checkpoint, further outputs."""
    P = inspect.Parameter
    names = [i.argument for i in spec.inputs] + [spec.output_argument]
    names += ["params"] if spec.settings else []
    names += list(spec.wildcards) + (["seed"] if spec.seeded else [])
    params = [P(n, P.POSITIONAL_OR_KEYWORD) for n in names]
    if spec.uses_device:
        params.append(P("device", P.POSITIONAL_OR_KEYWORD, default="auto"))
    if spec.checkpoint:
        params.append(P("checkpoint", P.POSITIONAL_OR_KEYWORD, default=None))
    params += [P(o.argument, P.POSITIONAL_OR_KEYWORD, default=None) for o in spec.outputs]
    return inspect.Signature(params)


_ENTRIES: dict[str, Callable[..., Any]] = {}


def entry(name: str) -> Callable[..., Any]:
    """The callable that runs stage `name`: its wrapper here, or the generic
    runner with the stage's signature (one object per rule: the specs of one
    rule, reconstruction_quality's, run alike)."""
    spec = registry.spec(registry.spec(name).rule)
    if spec.wrapper is not None:
        return globals()[spec.wrapper]
    if spec.name not in _ENTRIES or _ENTRIES[spec.name].__mogaf_spec__ is not spec:  # type: ignore[attr-defined]
        sig = signature(spec)

        def stage(*args: Any, **kwargs: Any) -> Any:
            bound = sig.bind(*args, **kwargs)
            bound.apply_defaults()
            return run(spec.name, **bound.arguments)

        stage.__signature__ = sig  # type: ignore[attr-defined]
        stage.__name__ = stage.__qualname__ = spec.rule
        stage.__doc__ = f"Stage {spec.name} ({spec.function}) through the generic runner (mogaf.registry)."
        stage.__mogaf_spec__ = spec  # type: ignore[attr-defined]
        _ENTRIES[spec.name] = stage
    return _ENTRIES[spec.name]


def __getattr__(name: str) -> Callable[..., Any]:
    """`mogaf.stages.<stage>` for every generic stage of the registry."""
    try:
        spec = registry.spec(name)
    except KeyError:
        raise AttributeError(f"module 'mogaf.stages' has no attribute {name!r}") from None
    if not spec.generic:
        raise AttributeError(name)
    return entry(name)


def rule_arguments(spec: registry.StageSpec, smk: Any) -> dict[str, Any]:
    """A stage's arguments from a Snakemake job (the `snakemake` object of a script)."""
    kwargs: dict[str, Any] = {}
    for i in spec.inputs:
        value = smk.input.get(i.argument)
        kwargs[i.argument] = list(value or []) if i.many else value
    kwargs[spec.output_argument] = smk.output[0]
    for o in spec.outputs:
        kwargs[o.argument] = smk.output.get(o.role)
    if spec.settings:
        kwargs["params"] = smk.params.get(spec.settings)
    for key in ("seed", "device", "checkpoint"):
        if getattr(spec, key):
            kwargs[key] = smk.params.get(key)
    if spec.threads_argument:
        kwargs["job_threads"] = smk.threads
    kwargs.update({w: smk.wildcards.get(w) for w in spec.wildcards})
    return kwargs


def run_rule(smk: Any) -> Any:
    """workflow/scripts/run_stage.py: the job's stage, found by its rule's name."""
    spec = registry.spec(smk.rule)
    return run_stage(
        entry(spec.name),
        smk.log[0],
        threads=smk.threads,
        torch_threads=spec.torch_threads,
        **rule_arguments(spec, smk),
    )


# ------------------------------------------------------------------ guards
def check_groups_cover(model: str, groups: str) -> None:
    """groups.h5 must give a group to every Gaussian of the model it is read
    with (a groups.h5 of another model would index past it, or leave some out)."""
    assigned, gaussians = _rows(groups, "group_id"), _rows(model, "fg/means")
    if assigned is not None and gaussians is not None and assigned != gaussians:
        raise input_error(
            groups,
            f"assigns groups to {assigned} Gaussians, but the model {model} has {gaussians}; "
            "rerun the grouping for this model",
        )


def check_ratio_text(ratio: str | float) -> float:
    """The {ratio} of a target path (ratio<r>): a number in (0, 1)."""
    from .split import check_ratio  # local: a stage's package (and torch) loads only when it runs

    try:
        r = float(ratio)
    except ValueError:
        raise MogafError(
            f"observation ratio '{ratio}' is not a number (target folder ratio<r> needs r in (0, 1))"
        ) from None
    return check_ratio(r)


# ------------------------------------------------------------------ library functions of generic stages
def split_stage(scene: str, out: str, ratio: str | float) -> Path:
    """The split stage's function (mogaf.split has no single entry)."""
    from .split import split_scene, write_split  # local: a stage's package (and torch) loads only when it runs

    return write_split(out, split_scene(scene, float(ratio)))


# ------------------------------------------------------------------ dedicated wrappers
def synthesize(out_dir: str, params: Mapping[str, Any], job_threads: int | None = None) -> Path:
    from .synth.generate import generate_scene  # local: a stage's package (and torch) loads only when it runs

    check_outputs({"out": out_dir}, directories=("out",))
    _check_synthetic_target(out_dir)
    return generate_scene(Path(out_dir), dict(params), threads=job_threads or 1)


def ingest(folder: str, out: str, layout: str, options: Mapping[str, Any], dataset: str, scene: str) -> Path:
    from .datasets import read_scene  # local: a stage's package (and torch) loads only when it runs
    from .scene import save_scene  # local: a stage's package (and torch) loads only when it runs

    check_outputs({"out": out}, [folder], folders=[folder])
    scene_model = read_scene(layout, Path(folder), dataset=dataset, scene=scene, options=dict(options))
    return save_scene(
        out, scene_model, config_digest=_digest("ingest", options, layout=layout, dataset=dataset, scene=scene)
    )


def forecast_group(
    model: str,
    groups: str,
    split: str,
    out: str,
    params: Mapping[str, Any],
    method: str,
    group: str,
    seed: int,
    device: str = "cpu",
    scene: str | None = None,
    priors: str | None = None,
) -> Path:
    from .forecast.stage import run_forecast_group  # local: a stage's package (and torch) loads only when it runs

    inputs = [model, groups, split, scene, priors]  # an optional input not given is None: skipped by both checks
    check_outputs({"out": out}, inputs)
    with stage_inputs(*inputs):
        check_groups_cover(model, groups)
        return run_forecast_group(
            model,
            groups,
            split,
            out,
            dict(params),
            method=method,
            job=group,
            seed=seed,
            device=device,
            scene_h5=scene,
            priors_h5=priors,
        )


def forecast_merge(
    model: str,
    groups: str,
    split: str,
    parts: list[str],
    out: str,
    params: Mapping[str, Any],
    method: str,
    seed: int = 0,
    device: str | None = None,
    job_threads: int | None = None,
    scene: str | None = None,
    priors: str | None = None,
) -> Path:
    from .forecast.stage import run_forecast_merge  # local: a stage's package (and torch) loads only when it runs

    inputs = [model, groups, split, scene, priors, *parts]  # None: an optional input not given
    check_outputs({"out": out}, inputs)
    with stage_inputs(*inputs):
        check_groups_cover(model, groups)
        return run_forecast_merge(
            model,
            groups,
            split,
            parts,
            out,
            dict(params),
            method=method,
            seed=seed,
            device=device,
            threads=job_threads,
            scene_h5=scene,
            priors_h5=priors,
        )


def evaluate(
    scene: str,
    split: str,
    model: str,
    groups: str,
    reconstruction_quality: str,
    grouping_quality: str,
    forecasts: Mapping[str, str],
    benchmarks: Mapping[str, str],
    out_metrics: str,
    out_renders: str,
    params: Mapping[str, Any],
    variant: str,
    ids: Mapping[str, str],
) -> Path:
    from .evaluate.stage import run_evaluate_stage  # local: a stage's package (and torch) loads only when it runs

    # groups.h5 is read for its lineage only: the forecasts, the model and the
    # grouping's quality must all come from this one grouping, and the
    # reconstruction quality from this model.
    inputs = [
        scene,
        split,
        model,
        groups,
        reconstruction_quality,
        grouping_quality,
        *forecasts.values(),
        *benchmarks.values(),
    ]
    check_outputs({"metrics": out_metrics, "renders": out_renders}, inputs, directories=("renders",))
    with stage_inputs(scene, split, model, groups, reconstruction_quality, grouping_quality, *forecasts.values()):
        check_made_from(reconstruction_quality, model)  # of this very model (refined.h5 vs recon.h5)
        check_groups_cover(model, groups)
        return run_evaluate_stage(
            scene=scene,
            split=split,
            model=model,
            reconstruction_quality=reconstruction_quality,
            grouping_quality=grouping_quality,
            forecasts=dict(forecasts),
            benchmarks=dict(benchmarks),
            out_metrics=out_metrics,
            out_renders=out_renders,
            params=dict(params),
            variant=variant,
            ids=dict(ids),
        )


def scene_report(
    renders: str,
    metrics: str,
    grouping_quality: str,
    reconstruction_quality: str,
    out_videos: str,
    out_quality: str,
) -> list[Path]:
    """A scene's videos page (a folder with its videos) and its quality figure, for the report."""
    from .report.pages import scene_report as write_scene_report

    check_outputs(
        {"videos": out_videos, "quality": out_quality},
        [renders, metrics, grouping_quality, reconstruction_quality],
        directories=("videos",),
    )
    return write_scene_report(renders, metrics, grouping_quality, reconstruction_quality, out_videos, out_quality)


def tables(
    metrics_files: list[str], out_files: list[str], params: Mapping[str, Any], ablations: Mapping[str, Any]
) -> list[Path]:
    from .report.tables import write_tables  # local: a stage's package (and torch) loads only when it runs

    check_outputs({f"table {i}": f for i, f in enumerate(out_files)}, metrics_files)
    return write_tables(metrics_files, out_files, dict(params), dict(ablations))


def scenes_table(metrics_files: list[str], out_md: str) -> Path:
    """The per-scene table of a grid's metrics.json files (mogaf.report.scenes), written atomically."""
    from .report.scenes import scenes  # local: a stage's package loads only when it runs

    check_outputs({"md": out_md}, metrics_files)
    text = scenes(metrics_files)
    with atomic_path(out_md) as tmp:
        Path(tmp).write_text(text)
    return Path(out_md)


def runtime_report(
    metrics_files: list[str], out_csv: str, out_md: str, out_png: str, params: Mapping[str, Any]
) -> list[Path]:
    from .report.runtime import write_runtime_report  # local: a stage's package (and torch) loads only when it runs

    check_outputs({"csv": out_csv, "md": out_md, "png": out_png}, metrics_files)
    return write_runtime_report(metrics_files, out_csv, out_md, out_png, dict(params))
