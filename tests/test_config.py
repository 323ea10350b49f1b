"""Config resolution: datasets, scene overrides, variants and shared artefacts."""

from __future__ import annotations

import pytest

import mogaf.config as mcfg
from mogaf.errors import MogafError
from support.paths import REPO

BASE = mcfg.with_defaults(mcfg.load_yaml("config/config.yaml"))
VARIANTS = mcfg.load_yaml("config/ablations.yaml")["variants"]


def prefixes(variant):
    cfg = mcfg.variant_config(BASE, VARIANTS, variant)
    stages = [
        "priors",
        "recon",
        "group",
        "rigid_init",
        "refine",
        "grouping_quality",
        "reconstruction_quality:recon",
        "reconstruction_quality:refine",
        "forecast:mogaf",
        "forecast:gcn",
        "evaluate",
    ]
    return {s: mcfg.artefact_prefix(s, BASE, cfg, variant) for s in stages}


def test_forecaster_variant_shares_everything_upstream():
    p = prefixes("no_masking")
    assert p["priors"] == p["recon"] == p["group"] == p["refine"] == p["grouping_quality"] == ""
    assert p["reconstruction_quality:refine"] == p["reconstruction_quality:recon"] == ""
    assert p["forecast:mogaf"] == "ablation/no_masking/"
    assert p["forecast:gcn"] == ""  # another method's forecast is unchanged


def test_grouping_variant_shares_reconstruction_only():
    p = prefixes("gaga4d")
    assert p["priors"] == p["recon"] == ""
    assert p["group"] == p["refine"] == p["grouping_quality"] == p["forecast:mogaf"] == "ablation/gaga4d/"
    assert p["reconstruction_quality:refine"] == "ablation/gaga4d/"  # the model was refined with these groups
    assert p["reconstruction_quality:recon"] == ""


def test_reconstruction_knob_invalidates_downstream():
    p = prefixes("rt_fast")
    assert p["priors"] == ""
    assert all(
        p[s] == "ablation/rt_fast/"
        for s in ("recon", "group", "refine", "grouping_quality", "forecast:mogaf", "forecast:gcn")
    )


def test_reconstruction_quality_is_of_the_model_the_forecasts_start_from():
    # one file per model: every variant forecasting from the shared recon.h5 shares the one of recon.h5
    for variant, model in (("lw_opt_fc", "refine"), ("lw_noopt_fc", "recon"), ("hc_noopt_nofc", "recon")):
        cfg = mcfg.variant_config(BASE, VARIANTS, variant)
        assert mcfg.reconstruction_quality_stage(cfg) == f"reconstruction_quality:{model}"
        assert prefixes(variant)[f"reconstruction_quality:{model}"] == ""
    cfg = mcfg.variant_config(BASE, {"n": {"overrides": {"reconstruction_quality": {"max_frames": 2}}}}, "n")
    p = {
        s: mcfg.artefact_prefix(s, BASE, cfg, "n")
        for s in ("refine", "forecast:mogaf", "grouping_quality", "reconstruction_quality:refine", "evaluate")
    }
    assert p == {
        "refine": "",
        "forecast:mogaf": "",
        "grouping_quality": "",
        "reconstruction_quality:refine": "ablation/n/",
        "evaluate": "ablation/n/",
    }


def test_grouping_quality_settings_touch_only_the_measurement():
    cfg = mcfg.variant_config(BASE, {"px": {"overrides": {"grouping_quality": {"pixels": "all"}}}}, "px")
    p = {
        s: mcfg.artefact_prefix(s, BASE, cfg, "px")
        for s in ("group", "refine", "forecast:mogaf", "grouping_quality", "evaluate")
    }
    assert p == {
        "group": "",
        "refine": "",
        "forecast:mogaf": "",
        "grouping_quality": "ablation/px/",
        "evaluate": "ablation/px/",
    }


def test_unrefined_input_variant():
    cfg = mcfg.variant_config(BASE, VARIANTS, "lw_noopt_fc")
    assert mcfg.forecast_input_stage(cfg) == "recon"
    p = prefixes("lw_noopt_fc")
    assert p["recon"] == p["group"] == "" and p["forecast:mogaf"] == "ablation/lw_noopt_fc/"


def test_variant_equal_to_default_shares_all():
    assert set(prefixes("lw_opt_fc").values()) - {""} == {"ablation/lw_opt_fc/"}
    assert prefixes("lw_opt_fc")["forecast:mogaf"] == ""  # same values as default: reused


def test_unknown_names_are_one_line_errors():
    with pytest.raises(MogafError, match="unknown dataset 'nope'"):
        mcfg.scene_dir(BASE, "nope", "x")
    with pytest.raises(MogafError, match="unknown scene 'nope' of dataset 'iphone'"):
        mcfg.scene_dir(BASE, "iphone", "nope")
    with pytest.raises(MogafError, match="unknown ablation variant"):
        mcfg.variant_config(BASE, VARIANTS, "nope")


def test_scene_overrides_and_paths():
    cfg = mcfg.deep_merge(
        BASE,
        {
            "datasets": {
                "mujoco": {
                    "overrides": {"recon": {"iterations": 7}},
                    "scene_overrides": {"scene3_collision": {"recon": {"iterations": 9}}},
                }
            }
        },
    )
    assert mcfg.scene_config(cfg, "mujoco", "scene1_close_proximity")["recon"]["iterations"] == 7
    assert mcfg.scene_config(cfg, "mujoco", "scene3_collision")["recon"]["iterations"] == 9
    assert mcfg.scene_dir(BASE, "iphone", "apple") == "data/iphone/apple"


def test_variant_keys_a_scene_override_sets_are_named():
    """scene_config merges the dataset's overrides and the scene's
    scene_overrides over a variant: the variant's keys they set are named
    (the workflow warns), those they do not set are not."""
    import copy

    cfg = copy.deepcopy(BASE)
    cfg["datasets"]["synthetic"]["overrides"] = {"recon": {"iterations": 7}}
    cfg["datasets"]["synthetic"]["scene_overrides"] = {"default": {"grouping": {"rigid_override": {"cube": 0}}}}
    overrides = {
        "recon": {"iterations": 5, "sh_degree": 1},
        "grouping": {"rigid_override": {"cube": 1, "box": 0}},
        "forecast": {"mogaf": {"iterations": 3}},
    }
    named = mcfg.variant_keys_set_for_scene(cfg, overrides, "synthetic", "default")
    assert named == ["recon.iterations", "grouping.rigid_override.cube"]
    assert mcfg.variant_keys_set_for_scene(cfg, overrides, "synthetic", "hard") == ["recon.iterations"]
    merged = mcfg.scene_config(mcfg.variant_config(cfg, {"v": {"overrides": overrides}}, "v"), "synthetic", "default")
    assert merged["recon"]["iterations"] == 7 and merged["grouping"]["rigid_override"] == {"cube": 0, "box": 0}


def test_rigidity_table():
    table = BASE["rigidity"]
    assert mcfg.rigidity_of("sphere_1", table) == 1
    assert mcfg.rigidity_of("Cloth", table) == 0
    assert mcfg.rigidity_of("teddy", table) == -1


def _stage_resolvers():
    from mogaf.evaluate.stage import run_evaluate_stage
    from mogaf.forecast.registry import make_forecaster
    from mogaf.grouping.params import resolve_params as grouping
    from mogaf.grouping.quality import run_grouping_quality_stage
    from mogaf.grouping.stage import run_rigid_init_stage
    from mogaf.priors import resolve_params as priors
    from mogaf.recon.params import resolve_params as recon
    from mogaf.reconstruction_quality.stage import run_reconstruction_quality_stage
    from mogaf.refine import resolve_params as refine
    from mogaf.synth.params import resolve_params as synthetic

    missing = "no/such/file.h5"  # the typo must be refused before any input is opened
    return {
        "synthetic": synthetic,
        "priors": priors,
        "recon": recon,
        "grouping": grouping,
        "refine": refine,
        "rigid_init": lambda p: run_rigid_init_stage(missing, missing, missing, p),
        "grouping_quality": lambda p: run_grouping_quality_stage(missing, missing, missing, missing, missing, p),
        "reconstruction_quality": lambda p: run_reconstruction_quality_stage(missing, missing, missing, missing, p),
        "forecast.mogaf": lambda p: make_forecaster("mogaf", p),
        "evaluate": lambda p: run_evaluate_stage(
            scene=missing,
            split=missing,
            model=missing,
            reconstruction_quality=missing,
            grouping_quality=missing,
            forecasts={},
            benchmarks={},
            out_metrics=missing,
            out_renders=missing,
            params=p,
            variant="",
            ids={},
        ),
    }


@pytest.mark.parametrize("section", sorted(_stage_resolvers()))
def test_every_stage_refuses_a_misspelt_parameter_by_name(section):
    with pytest.raises(MogafError, match=rf"^{section}: unknown parameter\(s\) lamda_typo \(known: .*\)$"):
        _stage_resolvers()[section]({"lamda_typo": 1})


def test_mogaf_paper_shares_its_forecast_when_only_the_structured_mode_changes():
    """mogaf_paper reads forecast.mogaf less `structured`, with its mode fixed:
    a variant changing only those keeps its forecast; one changing a shared
    setting (iterations) does not."""
    import copy

    def prefix(method, change):
        cfg = copy.deepcopy(BASE)
        change(cfg["forecast"]["mogaf"])
        return mcfg.artefact_prefix(f"forecast:{method}", BASE, cfg, "v")

    for change in (lambda s: s["structured"].update(context=8), lambda s: s.update(mode="paper")):
        assert prefix("mogaf_paper", change) == ""
        assert prefix("mogaf", change) == "ablation/v/"
    assert prefix("mogaf_paper", lambda s: s.update(iterations=5)) == "ablation/v/"


def test_the_shipped_configs_and_variants_set_nothing_without_effect():
    """Every shipped config layer over config/config.yaml sets no forecaster
    value that the others silence, nor does any variant over it, except the
    structured mode's variants under config/paper.yaml (mode: paper)."""
    base = mcfg.with_defaults(mcfg.load_yaml(REPO / "config" / "config.yaml"))
    variants = mcfg.load_yaml(REPO / "config" / "ablations.yaml")["variants"]
    layers = [
        p for p in sorted((REPO / "config").glob("*.yaml")) if "schema" not in p.name and p.name != "ablations.yaml"
    ]
    assert len(layers) >= 6 and len(variants) >= 5
    for path in layers:
        cfg = mcfg.with_defaults(mcfg.deep_merge(base, mcfg.load_yaml(path)))
        own, per_variant = mcfg.inert_forecaster_settings(cfg, variants)
        assert own == [], path.name
        paper = cfg["forecast"]["mogaf"]["mode"] == "paper"
        for name, inert in per_variant.items():
            if paper:
                assert all(key.startswith("structured.") and "mode is paper" in line for key, line in inert), name
            else:
                assert inert == [], (path.name, name)


def test_a_value_is_said_to_do_nothing_only_where_no_run_reads_it():
    base = mcfg.with_defaults(mcfg.load_yaml(REPO / "config" / "config.yaml"))

    def structured(**values):
        return {"forecast": {"mogaf": {"structured": values}}}

    variants = {
        "select": {"overrides": structured(combine="select")},
        "select_k4": {"overrides": structured(combine="select", backtest_neighbors=4)},
        "mogaf_only": {"overrides": {"forecast": {"methods": ["mogaf"]}}},
    }

    def inert(section):
        cfg = mcfg.with_defaults(mcfg.deep_merge(base, {"forecast": section}))
        own, per_variant = mcfg.inert_forecaster_settings(cfg, variants)
        return [key for key, _ in own], {name: [key for key, _ in v] for name, v in per_variant.items()}

    # a variant's own value that does nothing in it is listed under the variant
    assert inert({}) == ([], {"select": [], "select_k4": ["structured.backtest_neighbors"], "mogaf_only": []})
    # a config value that only a variant silences is not: that is what the variant is for
    assert inert({"mogaf": {"structured": {"backtest_neighbors": 8}}})[0] == []
    # a config value silenced in the config and in every variant is
    no_trend = {"mogaf": {"structured": {"candidates": ["frozen", "learned"], "trend_window": 4}}}
    assert inert(no_trend)[0] == ["structured.trend_window"]
    # the config runs no mogaf, but a variant does and reads its value: not listed
    assert inert({"methods": ["gcn"], "mogaf": {"lr": 0.02}})[0] == []
    variants.pop("mogaf_only")
    assert inert({"methods": ["gcn"], "mogaf": {"lr": 0.02}})[0] == ["lr"]
