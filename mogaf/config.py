"""Configuration: datasets, per-stage parameters, ablation variants, artefact paths.

Pure Python so that the Snakefile, the CLI and the tests share one logic.

Variants. An ablation or run-time-sweep variant is a named set of config
overrides (config/ablations.yaml). Its artefacts live under
`results/{dataset}/{scene}/ratio{r}/ablation/{variant}/` — but only for the
stages whose parameters (or whose upstream stages' parameters) the variant
changes; every other artefact is shared with the default pipeline, so a
sweep computes shared stages once.
"""

from __future__ import annotations

import copy
import fnmatch
import os
import re
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

from . import registry
from .errors import MogafError
from .forecast.params import METHODS, inert_settings, param_section, section_params
from .settings import section_defaults

# The stage graph (which config sections and upstream stages determine each
# artefact, and its file) comes from the one registry; forecasts depend on the
# method and evaluation on the methods listed, see _sections / _upstream.
STAGE_SECTIONS: dict[str, tuple[str, ...]] = registry.digest_sections()
STAGE_UPSTREAM: dict[str, tuple[str, ...]] = registry.upstream()
ARTEFACT_FILES: dict[str, str] = registry.artefact_files()
FORECAST_METHODS = METHODS
VARIANT_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


def deep_merge(base: Mapping[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    """Recursive merge; `override` wins; lists are replaced, not merged."""
    out = copy.deepcopy(dict(base))
    for key, value in override.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def with_defaults(config: Mapping[str, Any]) -> dict[str, Any]:
    """The config with every stage setting it leaves out at its default
    (config/config.yaml holds only what a user is expected to change;
    the defaults are the stages' settings dataclasses, mogaf.settings)."""
    return deep_merge(section_defaults(), config)


def _get(config: Mapping[str, Any], dotted: str) -> Any:
    node: Any = config
    for part in dotted.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return None
        node = node[part]
    return node


# ------------------------------------------------------------------ datasets
def dataset_config(config: Mapping[str, Any], dataset: str) -> Mapping[str, Any]:
    datasets = config.get("datasets", {})
    if dataset not in datasets:
        known = ", ".join(sorted(datasets)) or "none"
        raise MogafError(f"unknown dataset '{dataset}' (the config's datasets: {known})")
    return datasets[dataset]


def check_scene(config: Mapping[str, Any], dataset: str, scene: str) -> None:
    ds = dataset_config(config, dataset)
    scenes = ds.get("scenes")
    if scenes is not None and scene not in scenes:
        raise MogafError(f"unknown scene '{scene}' of dataset '{dataset}' (the config lists: {', '.join(scenes)})")


def scene_dir(config: Mapping[str, Any], dataset: str, scene: str) -> str:
    """Folder holding the scene's files (a template with {scene} in config)."""
    check_scene(config, dataset, scene)
    return dataset_config(config, dataset)["path"].format(scene=scene, dataset=dataset)


def dataset_layout(config: Mapping[str, Any], dataset: str) -> str:
    return dataset_config(config, dataset)["layout"]


def scene_config(config: Mapping[str, Any], dataset: str, scene: str) -> dict[str, Any]:
    """Config with the dataset's and the scene's overrides applied.

    datasets.<d>.overrides applies to every scene of the dataset and
    datasets.<d>.scene_overrides.<scene> to one scene; both may set any
    stage section (recon, priors, ...), e.g. fewer iterations for big grids.
    """
    ds = dataset_config(config, dataset)
    merged = deep_merge(config, ds.get("overrides") or {})
    return deep_merge(merged, (ds.get("scene_overrides") or {}).get(scene) or {})


def leaves(node: Any, prefix: tuple = ()) -> Iterator[tuple[tuple, Any]]:
    """(keys, value) of every value below nested mappings that is not itself
    a mapping (an empty mapping holds none)."""
    if isinstance(node, Mapping):
        for key, value in node.items():
            yield from leaves(value, (*prefix, key))
    else:
        yield prefix, node


def variant_keys_set_for_scene(
    config: Mapping[str, Any], overrides: Mapping[str, Any], dataset: str, scene: str
) -> list[str]:
    """The variant's settings (dotted) that the dataset's overrides or the
    scene's scene_overrides set too: those win (scene_config merges them
    last), so the variant does not change them for this scene."""
    ds = dataset_config(config, dataset)
    layers = [ds.get("overrides") or {}, (ds.get("scene_overrides") or {}).get(scene) or {}]
    return [
        ".".join(map(str, keys))
        for keys, _ in leaves(overrides or {})
        if any(depth_set(layer, list(keys)) == len(keys) for layer in layers)
    ]


def ingest_options(config: Mapping[str, Any], dataset: str, scene: str) -> dict[str, Any]:
    ds = dataset_config(config, dataset)
    options = dict(ds.get("options") or {})
    options.setdefault("rigidity", dict(config.get("rigidity") or {}))
    return options


def rigidity_of(name: str, table: Mapping[str, str]) -> int:
    """1 rigid, 0 non-rigid, -1 unknown: first fnmatch pattern that matches."""
    for pattern, kind in table.items():
        if fnmatch.fnmatch(name.lower(), pattern.lower()):
            return {"rigid": 1, "nonrigid": 0}.get(kind, -1)
    return -1


# ------------------------------------------------------------------ variants
def ablations_path(config: Mapping[str, Any], checkout: str | os.PathLike) -> Path:
    """The config's ablations_file: relative to the working folder, else to the checkout."""
    path = Path(config.get("ablations_file", "config/ablations.yaml"))
    return path if path.is_absolute() or path.exists() else Path(checkout) / path


def variant_config(config: Mapping[str, Any], variants: Mapping[str, Any], variant: str | None) -> dict[str, Any]:
    if not variant:
        return copy.deepcopy(dict(config))
    if variant not in variants:
        known = ", ".join(sorted(variants)) or "none"
        raise MogafError(f"unknown ablation variant '{variant}' (config/ablations.yaml defines: {known})")
    return deep_merge(config, variants[variant].get("overrides") or {})


def depth_set(config: Any, keys: Sequence[Any]) -> int:
    """How many leading `keys` `config` sets (nested mappings and lists)."""
    node, depth = config, 0
    for key in keys:
        if (
            isinstance(node, Mapping)
            and key in node
            or isinstance(node, list)
            and isinstance(key, int)
            and 0 <= key < len(node)
        ):
            node = node[key]
        else:
            break
        depth += 1
    return depth


def _overrides_set(variant: Mapping[str, Any], key: str) -> bool:
    """Whether a variant's overrides set forecast.mogaf.<key> themselves."""
    keys = ["forecast", "mogaf", *key.split(".")]
    return depth_set(variant.get("overrides") or {}, keys) == len(keys)


def inert_forecaster_settings(
    config: Mapping[str, Any], variants: Mapping[str, Any]
) -> tuple[list[tuple[str, str]], dict[str, list[tuple[str, str]]]]:
    """The forecaster values that do nothing (mogaf.forecast.params.inert_settings),
    split so that no line contradicts a run: (the config's own values that no
    variant reads either, {variant: the values its own overrides set that do
    nothing in it}). A config value that only some variant silences is not
    listed: that is what the variant is for."""
    base = dict(inert_settings(config["forecast"]))
    own: dict[str, list[tuple[str, str]]] = {}
    for name, variant in variants.items():
        inert = dict(inert_settings(variant_config(config, variants, name)["forecast"]))
        own[name] = [(key, line) for key, line in inert.items() if _overrides_set(variant, key)]
        base = {key: line for key, line in base.items() if key in inert or _overrides_set(variant, key)}
    return list(base.items()), own


def forecast_input_stage(config: Mapping[str, Any]) -> str:
    return "refine" if _get(config, "forecast.input") == "refined" else "recon"


def reconstruction_quality_stage(config: Mapping[str, Any]) -> str:
    """The reconstruction_quality artefact of the model the forecasts start from."""
    return f"reconstruction_quality:{forecast_input_stage(config)}"


def _stage_value(stage: str, config: Mapping[str, Any], key: str) -> Any:
    """What `stage` reads of config section `key`: a forecast method reads only
    its part of a shared section (mogaf_paper: forecast.mogaf less `structured`,
    mode fixed), so a change it does not read shares its artefacts."""
    value = _get(config, key)
    if (
        stage.startswith("forecast:")
        and key.startswith("forecast.")
        and key.count(".") == 1
        and isinstance(value, Mapping)
    ):
        method = stage.split(":", 1)[1]
        if key == f"forecast.{param_section(method)}":
            return section_params(method, value)
    return value


def _sections(stage: str, config: Mapping[str, Any]) -> tuple[str, ...]:
    if stage.startswith("forecast:"):
        method = stage.split(":", 1)[1]
        return (
            "seed",
            "device",
            "forecast.input",
            "forecast.groupwise",
            "forecast.jobs",
            "forecast.common",
            f"forecast.{param_section(method)}",
        )
    return STAGE_SECTIONS[stage]


def _upstream(stage: str, config: Mapping[str, Any]) -> tuple[str, ...]:
    if stage.startswith("forecast:"):
        return (forecast_input_stage(config), "group")
    if stage == "evaluate":
        return tuple(f"forecast:{m}" for m in config["forecast"]["methods"]) + (
            forecast_input_stage(config),
            "grouping_quality",
            reconstruction_quality_stage(config),
        )
    return STAGE_UPSTREAM[stage]


def stage_differs(stage: str, base: Mapping[str, Any], other: Mapping[str, Any]) -> bool:
    """Whether `other` changes the stage's parameters or any upstream stage's."""
    seen: set[str] = set()
    todo = [stage]
    while todo:
        s = todo.pop()
        if s in seen:
            continue
        seen.add(s)
        if any(_stage_value(s, base, key) != _stage_value(s, other, key) for key in _sections(s, other)):
            return True
        # Upstream stages follow the variant's own wiring (e.g. forecast.input).
        todo.extend(_upstream(s, other))
        todo.extend(_upstream(s, base))
    return False


def artefact_prefix(stage: str, base: Mapping[str, Any], variant_cfg: Mapping[str, Any], variant: str | None) -> str:
    """'' for artefacts shared with the default pipeline, else 'ablation/<v>/'."""
    if not variant or not stage_differs(stage, base, variant_cfg):
        return ""
    return f"ablation/{variant}/"


def ratio_dir(dataset: str, scene: str, ratio: str) -> str:
    return registry.RATIO_DIR.format(dataset=dataset, scene=scene, ratio=ratio).rstrip("/")


def check_variant_name(name: str) -> None:
    if not VARIANT_NAME.match(name):
        raise MogafError(f"ablation variant name '{name}' must be letters, digits, '_', '-' or '.'")


# Read once for the whole workflow or by the per-scene stages a variant shares
# (synthesize, ingest: the scene itself), never per variant: a variant setting
# one would be silently ignored.
NOT_PER_VARIANT = ("cache_dir", "ablations_file", "demo", "grid", "datasets", "rigidity", "synthetic", "report")


def check_variant_overrides(name: str, overrides: Mapping[str, Any]) -> None:
    """Refuse a variant that overrides what no variant can change."""
    fixed = [key for key in NOT_PER_VARIANT if key in (overrides or {})]
    if fixed:
        raise MogafError(
            f"ablation variant '{name}' overrides {', '.join(fixed)}: the scene and the workflow are the same for "
            "every variant (synthesize and ingest run once per scene); put it in a config file layered with "
            "--configfile instead"
        )


def check_variant(path: str | os.PathLike, name: str, overrides: Mapping[str, Any]) -> None:
    """One variant of the ablations file `path`: its name and what it overrides
    (the workflow and the CLI check every variant so); an error names `path`."""
    try:
        check_variant_name(name)
        check_variant_overrides(name, overrides)
    except MogafError as exc:
        raise MogafError(f"{os.fspath(path)}: {exc}") from None


def load_yaml(path: str | os.PathLike) -> dict[str, Any]:
    import yaml

    p = Path(path)
    try:
        with open(p) as fh:
            data = yaml.safe_load(fh) or {}
    except FileNotFoundError:
        raise MogafError(f"{p}: missing") from None
    except IsADirectoryError:
        raise MogafError(f"{p}: is a folder, not a YAML file") from None
    except OSError as exc:
        raise MogafError(f"{p}: cannot be read ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise MogafError(f"{p}: not UTF-8 text (byte {exc.start})") from None
    except yaml.YAMLError as exc:
        raise MogafError(f"{p}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise MogafError(f"{p}: expected a mapping at the top level")
    return data
