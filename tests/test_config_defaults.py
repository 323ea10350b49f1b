"""config/config.yaml writes out only what a user changes, each at the
library's default, and with the rest filled in (mogaf.config.with_defaults)
it is exactly the library's defaults; the schema (config/schema.yaml plus the
sections generated from the settings dataclasses) refuses keys and values the
library does not take."""

from __future__ import annotations

import copy
from typing import Any

import pytest
import yaml

from support.paths import REPO

CONFIG = REPO / "config" / "config.yaml"
SCHEMA = REPO / "config" / "schema.yaml"

# Keys the workflow injects from the top level of the config (mogaf.stages):
# priors and grouping get `seed`, recon and refine get `device`. They are left out of the
# stage sections (the schema refuses them there).
INJECTED = {"priors": {"seed"}, "grouping": {"seed"}, "recon": {"device"}}


def written_config() -> dict[str, Any]:
    with open(CONFIG) as fh:
        return yaml.safe_load(fh)


def load_config() -> dict[str, Any]:
    """config/config.yaml as the workflow and the CLI use it: defaults filled in."""
    from mogaf.config import with_defaults

    return with_defaults(written_config())


def library_defaults() -> dict[str, dict[str, Any]]:
    """section path -> the library's default dict, as the stages receive it."""
    import mogaf.evaluate
    import mogaf.grouping
    import mogaf.grouping.quality
    import mogaf.priors
    import mogaf.recon.params
    import mogaf.reconstruction_quality
    import mogaf.refine
    from mogaf.forecast.params import METHODS
    from mogaf.forecast.registry import defaults

    out = {
        "priors": mogaf.priors.DEFAULT_PARAMS,
        "recon": mogaf.recon.params.DEFAULT_PARAMS,
        "grouping": mogaf.grouping.DEFAULT_PARAMS,
        "rigid_init": mogaf.grouping.RIGID_INIT_DEFAULTS,
        "refine": mogaf.refine.REFINE_DEFAULTS,
        "evaluate": mogaf.evaluate.DEFAULT_PARAMS,
        "grouping_quality": mogaf.grouping.quality.DEFAULT_PARAMS,
        "reconstruction_quality": mogaf.reconstruction_quality.DEFAULT_PARAMS,
    }
    from mogaf.forecast.params import param_section

    # a method reading another's section (mogaf_paper: forecast.mogaf) has no section of its own
    out.update({f"forecast.{m}": defaults(m) for m in METHODS if param_section(m) == m})
    return {name: {k: v for k, v in d.items() if k not in INJECTED.get(name, set())} for name, d in out.items()}


def section(cfg: dict[str, Any], path: str) -> Any:
    for part in path.split("."):
        cfg = cfg[part]
    return cfg


def same_typed(a: Any, b: Any) -> bool:
    """Equal with the same types (1 vs 1.0 would change artefact digests)."""
    if type(a) is not type(b):
        return False
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(same_typed(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(same_typed(x, y) for x, y in zip(a, b))
    return a == b


@pytest.mark.parametrize("name", list(library_defaults()))
def test_section_equals_library_defaults(name):
    lib = library_defaults()[name]
    cfg = section(load_config(), name)
    assert sorted(cfg) == sorted(lib), (
        f"{name}: config only {sorted(set(cfg) - set(lib))}, library only {sorted(set(lib) - set(cfg))}"
    )
    wrong = {k: (cfg[k], lib[k]) for k in lib if not same_typed(cfg[k], lib[k])}
    assert not wrong, f"{name}: config vs library {wrong}"


def test_injected_keys_exist_and_are_the_top_level_defaults():
    import mogaf.priors
    import mogaf.recon.params

    cfg = load_config()
    assert mogaf.priors.DEFAULT_PARAMS["seed"] == cfg["seed"]
    assert mogaf.recon.params.DEFAULT_PARAMS["device"] == cfg["device"]


def test_resolved_params_are_the_library_defaults():
    """What the stages resolve from the config sections (with the injected
    keys) is exactly what they resolve from no parameters."""
    import mogaf.grouping
    import mogaf.priors
    import mogaf.recon.params
    import mogaf.refine
    from mogaf.forecast.base import merge_params
    from mogaf.forecast.params import METHODS
    from mogaf.forecast.registry import defaults
    from mogaf.forecast.stage import method_params

    cfg = load_config()
    assert mogaf.priors.resolve_params({**cfg["priors"], "seed": cfg["seed"]}) == mogaf.priors.resolve_params({})
    recon = {**cfg["recon"], "device": cfg["device"]}
    assert mogaf.recon.params.resolve_params(recon) == mogaf.recon.params.resolve_params({})
    assert mogaf.grouping.resolve_params({**cfg["grouping"], "seed": cfg["seed"]}) == mogaf.grouping.resolve_params({})
    assert mogaf.refine.resolve_params({**cfg["refine"], "device": cfg["device"]}) == mogaf.refine.resolve_params({})
    for m in METHODS:
        merged = merge_params(m, defaults(m), method_params(cfg["forecast"], m))
        assert same_typed(merged, defaults(m)), m


def test_forecast_common_holds_no_key():
    # constant_velocity and frozen take no parameters: any common key breaks them.
    assert load_config()["forecast"]["common"] == {}


# ------------------------------------------------------------------ schema
class SchemaError(Exception):
    pass


def validate(cfg: dict[str, Any]) -> None:
    """The workflow's check (workflow/rules/common.smk)."""
    from mogaf.schema import config_error, load_config_schema

    error = config_error(copy.deepcopy(cfg), load_config_schema(SCHEMA), [("config", cfg)])
    if error is not None:
        raise SchemaError(str(error))


def test_written_config_validates_and_sets_only_defaults():
    """What config.yaml writes out validates without the defaults, and every
    stage setting it writes is at the library's default."""
    from mogaf.settings import SECTIONS, defaults, section_class

    raw = written_config()
    validate(raw)
    for path in SECTIONS:
        node = raw
        for part in path.split("."):
            node = node.get(part) if isinstance(node, dict) else None
        if not isinstance(node, dict):
            continue
        lib = defaults(section_class(path))
        for key, value in node.items():
            if isinstance(value, dict) and isinstance(lib[key], dict):
                continue  # a nested section, checked on its own path
            assert same_typed(value, lib[key]), f"config.yaml {path}.{key}: {value!r}, library default {lib[key]!r}"


def test_config_validates():
    validate(load_config())


def test_layered_configs_and_ablation_variants_validate():
    import mogaf.config as mcfg

    base = load_config()
    for overlay in ("paper.yaml", "demo.yaml", "mujoco.yaml", "baselines_steps.yaml", "demo_seeds.yaml", "family.yaml"):
        validate(mcfg.deep_merge(base, mcfg.load_yaml(REPO / "config" / overlay)))  # overlays the docs name
    variants = mcfg.load_yaml(REPO / "config" / "ablations.yaml")["variants"]
    for name in variants:
        validate(mcfg.variant_config(base, variants, name))


def test_the_paper_config_keeps_the_papers_grouping_and_the_variant_restores_it():
    """The default holds an unlabelled group's resting members apart; the
    paper's config (and the variant joined_still) keep them in the group, as
    the paper does, so its pipeline is the paper's method. Both keep the
    first group a Gaussian joins; the variant mask_majority alone changes that."""
    import mogaf.config as mcfg
    from mogaf.grouping.params import load_settings

    base = load_config()
    paper = mcfg.deep_merge(base, mcfg.load_yaml(REPO / "config" / "paper.yaml"))
    variants = mcfg.load_yaml(REPO / "config" / "ablations.yaml")["variants"]
    joined = mcfg.variant_config(base, variants, "joined_still")
    assert load_settings(base["grouping"]).split_still_members == "unlabelled"
    assert load_settings(paper["grouping"]).split_still_members == "never"
    assert load_settings(joined["grouping"]).split_still_members == "never"
    majority = mcfg.variant_config(base, variants, "mask_majority")
    assert load_settings(base["grouping"]).mask_majority is False
    assert load_settings(paper["grouping"]).mask_majority is False
    assert load_settings(joined["grouping"]).mask_majority is False
    assert load_settings(majority["grouping"]).mask_majority is True
    assert load_settings(majority["grouping"]).split_still_members == "unlabelled"  # one change per variant


def test_family_draws_layer_adds_draws_of_family_scenes_and_changes_nothing_else():
    """config/family_draws.yaml over the family adds three draws of some of
    its scenes, each the family scene's settings with another generator
    seed, and changes no other setting, so the family's own runs are not rerun."""
    import copy

    import mogaf.config as mcfg

    family = mcfg.deep_merge(
        mcfg.deep_merge(load_config(), mcfg.load_yaml(REPO / "config" / "demo.yaml")),
        mcfg.load_yaml(REPO / "config" / "family.yaml"),
    )
    draws = mcfg.deep_merge(family, mcfg.load_yaml(REPO / "config" / "family_draws.yaml"))
    validate(draws)
    scenes = family["datasets"]["synthetic"]["scenes"]
    added = [s for s in draws["datasets"]["synthetic"]["scenes"] if s not in scenes]
    assert draws["datasets"]["synthetic"]["scenes"][: len(scenes)] == scenes and added
    base_of = {name: name.rsplit("_d", 1)[0] for name in added}
    assert sorted(added) == sorted(f"{base}_d{k}" for base in set(base_of.values()) for k in (1, 2, 3))
    assert set(base_of.values()) <= set(scenes)
    seeds = set()
    for name, base in base_of.items():
        own = dict(draws["synthetic"][name])
        seeds.add(own.pop("seed"))
        assert own == {k: v for k, v in family["synthetic"][base].items() if k != "seed"}, name
    assert len(seeds) == len(added) and not seeds & {family["synthetic"][s]["seed"] for s in scenes if s != "default"}
    # without the added scenes, the layered config is the family's
    rest = copy.deepcopy(draws)
    rest["datasets"]["synthetic"]["scenes"] = scenes
    for name in added:
        del rest["synthetic"][name]
    assert rest == family


def test_demo_seeds_layer_adds_scenes_and_leaves_the_demo_as_it_is():
    """config/demo_seeds.yaml over the demo's config adds the seeded scenes and
    their grid and changes no other setting, so the demo scene's jobs read the
    same config (a run beside `make demo` reused its metrics.json, 2026-11-25)."""
    import mogaf.config as mcfg

    demo = mcfg.deep_merge(load_config(), mcfg.load_yaml(REPO / "config" / "demo.yaml"))
    seeds = mcfg.deep_merge(demo, mcfg.load_yaml(REPO / "config" / "demo_seeds.yaml"))
    added = {"default_s1", "default_s2", "default_s3", "default_s4"}
    assert set(seeds["datasets"]["synthetic"]["scenes"]) == set(demo["datasets"]["synthetic"]["scenes"]) | added
    for name in demo["synthetic"]:
        assert seeds["synthetic"][name] == demo["synthetic"][name], name
    for name in added:
        assert seeds["synthetic"][name]["preset"] == "default" and seeds["synthetic"][name]["seed"] > 0
    assert {k: v for k, v in seeds["datasets"]["synthetic"].items() if k != "scenes"} == {
        k: v for k, v in demo["datasets"]["synthetic"].items() if k != "scenes"
    }
    changed = {k for k in seeds if seeds[k] != demo[k]}
    assert changed == {"datasets", "synthetic", "grid"}


@pytest.mark.parametrize(
    "override",
    [
        {"recon": {"iteratons": 100}},  # misspelt key
        {"recon": {"iterations": "many"}},  # wrong type
        {"recon": {"silhouette": "maybe"}},  # not one of the library's choices
        {"recon": {"device": "cpu"}},  # injected from the top level, not a section key
        {"priors": {"seed": 1}},
        {"grouping": {"seed": 1}},
        {"priors": {"grid_stride": 0}},
        {"grouping": {"front_fraction": 0.0}},
        {"rigid_init": {"weight": "uniform"}},
        {"refine": {"lambda_rigid": -1.0}},
        {"refine": {"recon": {"w_rgbb": 1.0}}},
        {"forecast": {"mogaf": {"num_layer": 5}}},
        {"forecast": {"ode": {"ode_layers": 1}}},
        {"forecast": {"frozen": {"lr": 0.1}}},
        {"forecast": {"common": {"lr": 0.1}}},  # frozen / constant_velocity are listed
        {"evaluate": {"lpip": False}},
    ],
)
def test_schema_refuses(override):
    import mogaf.config as mcfg

    with pytest.raises(SchemaError):
        validate(mcfg.deep_merge(load_config(), override))


def test_schema_accepts_overrides_the_library_accepts():
    import mogaf.config as mcfg

    base = load_config()
    for override in (
        {"recon": {"iterations_scale": 0.25, "silhouette": "off"}},
        {"forecast": {"mogaf": {"num_layers": 5, "masking": False}}},
        {"forecast": {"methods": ["mogaf", "ode"], "common": {"num_threads": 2}}},
        {"grouping": {"method": "gaga4d", "pca_components": 3, "rigid_override": {"ball": 1}}},
        {"refine": {"recon": {"w_track": 0.0}}},
        {"priors": {"depth_sources": "shipped"}},
    ):
        validate(mcfg.deep_merge(base, override))
