"""The stage registry is the one description of the stage graph: the CLI, the
artefact tables and the rule outputs must all follow it."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

import pytest

import mogaf.cli as cli
import mogaf.config as mcfg
import mogaf.registry as reg
import mogaf.stages as stages

RULES = Path(__file__).resolve().parents[1] / "workflow" / "rules"


@pytest.mark.parametrize("spec", reg.STAGES, ids=lambda s: s.name)
def test_spec_matches_its_function(spec):
    fn = getattr(stages, spec.function)
    args = set(inspect.signature(fn).parameters)
    wanted = {i.argument for i in spec.inputs} | {spec.output_argument}
    if spec.settings:
        wanted.add("params")
    if spec.seeded:
        wanted.add("seed")
    if spec.device:
        wanted.add("device")
    if spec.checkpoint:
        wanted.add("checkpoint")
    assert wanted <= args, f"{spec.name}: {sorted(wanted - args)} not arguments of mogaf.stages.{spec.function}"


def test_upstream_names_are_stages():
    for spec in reg.STAGES:
        for up in spec.upstream:
            assert up in reg.BY_NAME, (spec.name, up)


def test_cli_subcommands_follow_the_registry():
    assert set(cli.STAGES) == {s.cli for s in reg.STAGES if s.cli}
    parser = cli.build_parser()
    for spec in reg.STAGES:
        if not spec.cli:
            continue
        sub = parser._subparsers._group_actions[0].choices[spec.cli]  # noqa: SLF001 (argparse keeps no public map)
        options = {a.option_strings[0].lstrip("-"): a.required for a in sub._actions if a.option_strings}
        for i in spec.inputs:
            assert options.get(i.option) == i.required, (spec.cli, i.option)
        assert options.get("out") is True


def test_config_tables_follow_the_registry():
    for spec in reg.STAGES:
        if spec.digest_sections is None:
            assert spec.name not in mcfg.STAGE_SECTIONS
            continue
        assert mcfg.STAGE_SECTIONS[spec.name] == spec.digest_sections
        if spec.output and not spec.per_scene:
            assert mcfg.ARTEFACT_FILES[spec.name] == spec.output


@pytest.mark.parametrize("spec", [s for s in reg.STAGES if s.output and ":" not in s.name], ids=lambda s: s.name)
def test_rule_writes_the_registered_artefact(spec):
    text = (RULES / f"{spec.name}.smk").read_text()
    rule = re.search(rf"^(?:rule|checkpoint) {spec.name}:\n(.*?)(?=^rule |^checkpoint |\Z)", text, re.S | re.M)
    assert rule, f"no rule {spec.name} in {spec.name}.smk"
    output = re.search(r"^    output:\n(.*?)(?=^    \w+:)", rule.group(1), re.S | re.M).group(1)
    assert f'artefact("{spec.name}")' in output


def test_rule_output_patterns():
    assert reg.rule_output("recon") == "results/{dataset}/{scene}/ratio{ratio}/{prefix}recon.h5"
    assert reg.rule_output("split") == "results/{dataset}/{scene}/ratio{ratio}/split.h5"
    assert reg.rule_output("ingest") == "results/{dataset}/{scene}/scene.h5"
    with pytest.raises(KeyError):
        reg.rule_output("forecast_group")
