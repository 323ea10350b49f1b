"""Stage entry points: explicit paths in, artefact out.

The Snakemake scripts in workflow/scripts/ and the CLI (`python -m mogaf`)
call these and nothing else. Each writes its artefact atomically; a bad input
raises MogafError, which `run_stage` turns into one line and exit status 1.
Each declares the artefacts it reads (`mogaf.artefact.stage_inputs`): they
must share one lineage, and what it writes records them. Each refuses, before
it opens anything for writing, an output that would overwrite or delete one
of its inputs or write into a dataset folder (`mogaf.paths.check_outputs`).
"""

from __future__ import annotations

import logging
import numbers
import os
import sys
import time
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from .artefact import check_made_from, config_digest, open_artefact, stage_inputs, write_error
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


def set_threads(threads: int | None) -> None:
    """Torch's thread count; None leaves torch's default."""
    if threads is None:
        return
    if isinstance(threads, bool) or not isinstance(threads, numbers.Integral) or threads < 1:
        raise MogafError(f"threads must be a positive integer, got {threads!r}")
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
    fn: Callable[..., Any], log_path: str | os.PathLike | None = None, *, threads: int | None = None, **kwargs: Any
) -> Any:
    """Run one stage; a MogafError becomes one line on stderr and exit 1,
    a warning one line in the log."""
    start = time.perf_counter()
    logging_ready = False
    try:
        _setup_logging(log_path)
        logging_ready = True
        set_threads(threads)
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


def _check_groups_cover(model: str, groups: str) -> None:
    """groups.h5 must give a group to every Gaussian of the model it is read
    with (a groups.h5 of another model would index past it, or leave some out)."""
    assigned, gaussians = _rows(groups, "group_id"), _rows(model, "fg/means")
    if assigned is not None and gaussians is not None and assigned != gaussians:
        raise input_error(
            groups,
            f"assigns groups to {assigned} Gaussians, but the model {model} has {gaussians}; "
            "rerun the grouping for this model",
        )


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


# ------------------------------------------------------------------ stages
def synthesize(out_dir: str, params: Mapping[str, Any]) -> Path:
    from .synth.generate import generate_scene  # local: a stage's package (and torch) loads only when it runs

    check_outputs({"out": out_dir}, directories=("out",))
    _check_synthetic_target(out_dir)
    return generate_scene(Path(out_dir), dict(params))


def ingest(folder: str, out: str, layout: str, options: Mapping[str, Any], dataset: str, scene: str) -> Path:
    from .datasets import read_scene  # local: a stage's package (and torch) loads only when it runs
    from .scene import save_scene  # local: a stage's package (and torch) loads only when it runs

    check_outputs({"out": out}, [folder], folders=[folder])
    scene_model = read_scene(layout, Path(folder), dataset=dataset, scene=scene, options=dict(options))
    return save_scene(
        out, scene_model, config_digest=_digest("ingest", options, layout=layout, dataset=dataset, scene=scene)
    )


def split(scene: str, out: str, ratio: str | float) -> Path:
    from .split import (  # local: a stage's package (and torch) loads only when it runs
        check_ratio,
        split_scene,
        write_split,
    )

    check_outputs({"out": out}, [scene])
    try:
        r = float(ratio)
    except ValueError:
        raise MogafError(
            f"observation ratio '{ratio}' is not a number (target folder ratio<r> needs r in (0, 1))"
        ) from None
    check_ratio(r)
    with stage_inputs(scene):
        return write_split(out, split_scene(scene, r))


def priors(scene: str, split: str, out: str, params: Mapping[str, Any], seed: int) -> Path:
    from .priors.stage import run_priors_stage  # local: a stage's package (and torch) loads only when it runs

    check_outputs({"out": out}, [scene, split])
    with stage_inputs(scene, split):
        return run_priors_stage(scene, split, out, {**params, "seed": seed})


def recon(
    scene: str,
    split: str,
    priors: str,
    out: str,
    params: Mapping[str, Any],
    seed: int,
    device: str = "auto",
    checkpoint: str | None = None,
) -> Path:
    from .recon.stage import run_recon_stage  # local: a stage's package (and torch) loads only when it runs

    check_outputs({"out": out, "checkpoint": checkpoint}, [scene, split, priors])
    with stage_inputs(scene, split, priors):
        return run_recon_stage(
            scene, split, priors, out, {**params, "device": device}, seed=seed, checkpoint=checkpoint, progress=False
        )


def group(model: str, priors: str, scene: str, out: str, params: Mapping[str, Any], seed: int = 0) -> Path:
    from .grouping.stage import run_group_stage  # local: a stage's package (and torch) loads only when it runs

    check_outputs({"out": out}, [model, priors, scene])
    with stage_inputs(model, priors, scene):
        return run_group_stage(model, priors, scene, out, {**params, "seed": seed})


def rigid_init(model: str, groups: str, out: str, params: Mapping[str, Any]) -> Path:
    from .grouping.stage import run_rigid_init_stage  # local: a stage's package (and torch) loads only when it runs

    check_outputs({"out": out}, [model, groups])
    with stage_inputs(model, groups):
        _check_groups_cover(model, groups)
        return run_rigid_init_stage(model, groups, out, dict(params))


def refine(
    model: str,
    groups: str,
    rigid: str | None,
    priors: str,
    scene: str,
    split: str,
    out: str,
    params: Mapping[str, Any],
    seed: int,
    device: str = "auto",
    checkpoint: str | None = None,
) -> Path:
    from .refine.stage import run_refine_stage  # local: a stage's package (and torch) loads only when it runs

    check_outputs({"out": out, "checkpoint": checkpoint}, [model, groups, rigid, priors, scene, split])
    with stage_inputs(model, groups, rigid, priors, scene, split):
        _check_groups_cover(model, groups)
        return run_refine_stage(
            model,
            groups,
            rigid,
            priors,
            scene,
            split,
            out,
            {**params, "device": device},
            seed=seed,
            checkpoint=checkpoint,
            progress=False,
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
) -> Path:
    from .forecast.stage import run_forecast_group  # local: a stage's package (and torch) loads only when it runs

    check_outputs({"out": out}, [model, groups, split])
    with stage_inputs(model, groups, split):
        _check_groups_cover(model, groups)
        return run_forecast_group(
            model, groups, split, out, dict(params), method=method, job=group, seed=seed, device=device
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
) -> Path:
    from .forecast.stage import run_forecast_merge  # local: a stage's package (and torch) loads only when it runs

    check_outputs({"out": out}, [model, groups, split, *parts])
    with stage_inputs(model, groups, split, *parts):
        _check_groups_cover(model, groups)
        return run_forecast_merge(model, groups, split, parts, out, dict(params), method=method, seed=seed)


def grouping_quality(
    grouped_model: str, groups: str, scene: str, split: str, out: str, params: Mapping[str, Any]
) -> Path:
    from .grouping.quality import (
        run_grouping_quality_stage,  # local: a stage's package (and torch) loads only when it runs
    )

    check_outputs({"out": out}, [grouped_model, groups, scene, split])
    with stage_inputs(grouped_model, groups, scene, split):
        _check_groups_cover(grouped_model, groups)
        return run_grouping_quality_stage(grouped_model, groups, scene, split, out, dict(params))


def reconstruction_quality(model: str, scene: str, split: str, out: str, params: Mapping[str, Any]) -> Path:
    # local: a stage's package (and torch) loads only when it runs
    from .reconstruction_quality.stage import run_reconstruction_quality_stage

    check_outputs({"out": out}, [model, scene, split])
    with stage_inputs(model, scene, split):
        return run_reconstruction_quality_stage(model, scene, split, out, dict(params))


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
        _check_groups_cover(model, groups)
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


def export(
    model: str,
    forecast: str,
    scene: str,
    split: str,
    out: str,
    params: Mapping[str, Any],
    ply_dir: str | None = None,
) -> Path:
    """index.json at `out` and the PLY files it lists in `ply_dir` (default: ply/ beside it)."""
    from .export import ply_folder  # local: a stage's package (and torch) loads only when it runs
    from .export.stage import run_export_stage

    plys = ply_dir if ply_dir is not None else ply_folder(out)
    check_outputs({"out": out, "ply": plys}, [model, forecast, scene, split], directories=("ply",))
    with stage_inputs(model, forecast, scene, split):
        check_made_from(forecast, model)  # poses of this very model's Gaussians (refined.h5 vs recon.h5)
        return run_export_stage(model, forecast, scene, split, out, dict(params), ply_dir=plys)


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


def runtime_report(
    metrics_files: list[str], out_csv: str, out_md: str, out_png: str, params: Mapping[str, Any]
) -> list[Path]:
    from .report.runtime import write_runtime_report  # local: a stage's package (and torch) loads only when it runs

    check_outputs({"csv": out_csv, "md": out_md, "png": out_png}, metrics_files)
    return write_runtime_report(metrics_files, out_csv, out_md, out_png, dict(params))
