"""The stage registry is the one description of the stage graph: the generic
runner's calls, the CLI, the artefact tables, the rules' inputs, outputs,
logs and scripts must all follow it."""

from __future__ import annotations

import inspect
import re
import subprocess
import sys
from pathlib import Path

import pytest

import mogaf.cli as cli
import mogaf.config as mcfg
import mogaf.registry as reg
import mogaf.stages as stages

REPO = Path(__file__).resolve().parents[1]
RULES = REPO / "workflow" / "rules"
SCRIPTS = REPO / "workflow" / "scripts"
GENERIC = [s for s in reg.STAGES if s.generic]


def _rule_block(rule: str) -> str:
    for path in RULES.glob("*.smk"):
        text = path.read_text()
        found = re.search(rf"^(?:rule|checkpoint) {rule}:\n(.*?)(?=^\S|\Z)", text, re.S | re.M)
        if found:
            return found.group(1)
    raise AssertionError(f"no rule {rule} in workflow/rules")


def _directive(block: str, name: str) -> str:
    found = re.search(rf"^    {name}:\n(.*?)(?=^    \w+:|\Z)", block, re.S | re.M)
    return found.group(1) if found else ""


@pytest.mark.parametrize("spec", GENERIC, ids=lambda s: s.name)
def test_generic_function_takes_the_calling_convention(spec):
    """function(*inputs, out, [params], **keywords): the positions and keywords the runner passes."""
    fn = reg.load(spec.function)
    params = inspect.signature(fn).parameters
    positional = [p for p in params.values() if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)]
    wanted = len(spec.inputs) + 1 + (1 if spec.settings else 0)
    assert len(positional) >= wanted, f"{spec.function}: takes {len(positional)} positional arguments, not {wanted}"
    keywords = set(spec.wildcards) | {o.argument for o in spec.outputs} | {k for k, _ in spec.fixed}
    keywords |= {k for k in ("seed", "device") if getattr(spec, k) == "kwarg"}
    keywords |= {"checkpoint"} if spec.checkpoint else set()
    missing = {k for k in keywords if k not in params}
    assert not missing, f"{spec.function}: no argument(s) {sorted(missing)}"


@pytest.mark.parametrize("spec", [s for s in reg.STAGES if not s.generic], ids=lambda s: s.name)
def test_wrapper_takes_the_specs_arguments(spec):
    """A dedicated wrapper (mogaf.stages) takes what the script, CLI and runner pass it."""
    args = set(inspect.signature(stages.entry(spec.name)).parameters)
    wanted = {i.argument for i in spec.inputs} | {spec.output_argument} | set(spec.wildcards)
    wanted |= {o.argument for o in spec.outputs} | ({"params"} if spec.settings else set())
    wanted |= {k for k in ("seed", "device", "checkpoint") if getattr(spec, k)}
    assert wanted <= args, f"{spec.name}: {sorted(wanted - args)} not arguments of mogaf.stages.{spec.wrapper}"


def test_python_entries_keep_their_signatures():
    """`mogaf.stages.<stage>` is the generic runner with the stage's arguments, in the old order."""
    sig = {name: list(inspect.signature(getattr(stages, name)).parameters) for name in ("split", "priors", "refine")}
    assert sig["split"] == ["scene", "out", "ratio"]
    assert sig["priors"] == ["scene", "split", "out", "params", "seed"]
    assert sig["refine"] == [
        *("model", "groups", "rigid", "priors", "scene", "split", "out", "params", "seed", "device", "checkpoint"),
    ]
    assert stages.reconstruction_quality is stages.entry("reconstruction_quality:refine")
    with pytest.raises(AttributeError):
        stages.no_such_stage  # noqa: B018


def test_sources_and_guards_name_what_exists():
    for spec in reg.STAGES:
        for up in spec.upstream:
            assert up in reg.BY_NAME, (spec.name, up)
        args = {i.argument for i in spec.inputs} | set(spec.wildcards)
        for i in spec.inputs:
            if isinstance(i.source, str):
                assert i.source in reg.BY_NAME, (spec.name, i.argument, i.source)
            if i.only_if:
                assert callable(reg.load(i.only_if[0])) and i.only_if[1] in args, (spec.name, i.argument)
        for guard in spec.guards:
            assert callable(reg.load(guard.check)), (spec.name, guard.check)
            assert set(guard.arguments) <= args, (spec.name, guard)


def test_static_sources_are_upstream():
    """What a variant shares (mogaf.config) follows the inputs: every variant-shared source is upstream."""
    for spec in reg.STAGES:
        if spec.digest_sections is None or spec.name == "evaluate":
            continue
        closure, todo = set(), list(spec.upstream)
        while todo:
            s = todo.pop()
            if s not in closure:
                closure.add(s)
                todo += list(reg.BY_NAME[s].upstream)
        for i in spec.inputs:
            if isinstance(i.source, str) and reg.BY_NAME[i.source].digest_sections is not None:
                assert i.source in closure, (spec.name, i.source)


def test_cli_subcommands_follow_the_registry():
    assert set(reg.commands()) == {s.cli for s in reg.STAGES if s.cli}
    parser = cli.build_parser()
    choices = parser._subparsers._group_actions[0].choices  # noqa: SLF001 (argparse keeps no public map)
    for spec in reg.STAGES:
        if not spec.cli:
            continue
        sub = choices[spec.cli]
        options = {a.option_strings[0].lstrip("-"): a.required for a in sub._actions if a.option_strings}
        for i in spec.inputs:
            assert options.get(i.cli_option) == (i.required and not i.many), (spec.cli, i.cli_option)
        assert options.get("out") is True
        for w in spec.wildcards:
            assert w in options, (spec.cli, w)
        assert ("checkpoint" in options) == spec.checkpoint


def test_config_tables_follow_the_registry():
    for spec in reg.STAGES:
        if spec.digest_sections is None:
            assert spec.name not in mcfg.STAGE_SECTIONS
            continue
        assert mcfg.STAGE_SECTIONS[spec.name] == spec.digest_sections
        if spec.output and not spec.per_scene:
            assert mcfg.ARTEFACT_FILES[spec.name] == spec.output


@pytest.mark.parametrize("spec", [s for s in reg.STAGES if s.output], ids=lambda s: s.name)
def test_rule_follows_its_spec(spec):
    """Output, log and benchmark from the registry; a generic stage's inputs,
    params and script too (the rule file says only what is its own: threads,
    resources and comments)."""
    block = _rule_block(spec.rule)
    assert f'artefact("{spec.rule}")' in _directive(block, "output")
    for o in spec.outputs:
        assert f'artefact("{spec.rule}", "{o.role}")' in _directive(block, "output")
    assert f'log_file("{spec.rule}")' in _directive(block, "log")
    bench = _directive(block, "benchmark")
    assert not bench or f'benchmark_tsv("{spec.rule}")' in bench
    assert "results/" not in block, "a path pattern written out in the rule: use mogaf.registry's"
    script = _directive(block, "script").strip().strip('"')
    if spec.generic:
        assert f'unpack(stage_inputs("{spec.rule}"))' in _directive(block, "input")
        assert f'**stage_params("{spec.rule}")' in _directive(block, "params") or not _directive(block, "params")
        assert script == "../scripts/run_stage.py"
    assert (SCRIPTS / Path(script).name).is_file()


def test_scripts_are_the_generic_one_and_the_wrappers():
    """One script for every stage that the generic runner fits (and forecast's
    wrappers, which take its arguments); the other wrappers have their own."""
    expected = {"run_stage.py", "ingest.py", "synthesize.py", "evaluate.py"}
    expected |= {"tables.py", "runtime_report.py", "scene_report.py", "scenes_table.py"}
    assert {p.name for p in SCRIPTS.glob("*.py")} == expected


def test_path_patterns():
    assert reg.rule_output("recon") == "results/{dataset}/{scene}/ratio{ratio}/{prefix}recon.h5"
    assert reg.rule_output("split") == "results/{dataset}/{scene}/ratio{ratio}/split.h5"
    assert reg.rule_output("ingest") == "results/{dataset}/{scene}/scene.h5"
    assert reg.rule_output("forecast_group") == (
        "results/{dataset}/{scene}/ratio{ratio}/{prefix}forecast/{method}/group{group}.h5"
    )
    assert reg.rule_output("reconstruction_quality") == (
        "results/{dataset}/{scene}/ratio{ratio}/{prefix}reconstruction_quality/{model}.h5"
    )
    assert reg.rule_output("reconstruction_quality:refine").endswith("{prefix}reconstruction_quality/refined.h5")
    assert reg.rule_output("evaluate", "renders") == "results/{dataset}/{scene}/ratio{ratio}/{prefix}renders"
    from mogaf.export import ply_folder

    assert reg.rule_output("export", "ply") == ply_folder(reg.rule_output("export"))
    assert reg.job_path("log", "split") == "results/{dataset}/{scene}/ratio{ratio}/logs/split.log"
    assert reg.job_path("benchmark", "ingest") == "results/{dataset}/{scene}/benchmarks/ingest.tsv"
    assert reg.job_path("log", "forecast_group") == (
        "results/{dataset}/{scene}/ratio{ratio}/{prefix}logs/forecast_{method}_group{group}.log"
    )
    assert reg.job_path("checkpoint", "recon") == "results/{dataset}/{scene}/ratio{ratio}/{prefix}checkpoints/recon.pt"
    assert reg.job_path("log", "tables", scope="tables") == "results/tables/logs/tables.log"
    with pytest.raises(KeyError):
        reg.rule_output("no_such_stage")
    with pytest.raises(KeyError):
        reg.rule_output("recon", "ply")


def test_stage_sections_and_method_names_reach_the_schema_from_their_tables():
    """A stage's config section needs no line of its own in config/schema.yaml
    or mogaf.settings.SECTIONS, and the method names none in the schema."""
    from mogaf.forecast.params import METHOD_TABLE
    from mogaf.schema import load_config_schema
    from mogaf.settings import SECTIONS

    schema = load_config_schema(REPO / "config" / "schema.yaml")
    for spec in reg.STAGES:
        if spec.settings_class:
            assert SECTIONS[spec.settings] == (spec.settings_class, spec.settings)
            assert schema["properties"][spec.settings] == {"$ref": f"#/definitions/{spec.settings}"}
    raw = (REPO / "config" / "schema.yaml").read_text()
    assert "recon:" not in raw and "mogaf_paper" not in raw
    forecast = schema["properties"]["forecast"]
    assert forecast["properties"]["methods"]["items"]["enum"] == [m.name for m in METHOD_TABLE]
    assert set(forecast["properties"]) >= {m.name for m in METHOD_TABLE if not m.section}


def test_the_dags_predicates_load_without_torch():
    """Snakemake's own process calls the inputs' `only_if` predicates while it
    builds the DAG: their modules must not import torch (a second or two and
    hundreds of MB in the scheduler, on every run and every dry run)."""
    code = (
        "import sys, mogaf.registry as r\n"
        "names = [i.only_if[0] for s in r.STAGES for i in s.inputs if i.only_if]\n"
        "assert names, 'no predicate'\n"
        "[r.load(n) for n in names]\n"
        "print('torch' in sys.modules)"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == "False"
