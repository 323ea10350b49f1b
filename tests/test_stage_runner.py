"""The generic stage runner (mogaf.stages.run): a stage is one StageSpec, and
the runner, its Python entry and its CLI subcommand follow from it. A toy
stage (tests/support/toy_stage.py) is registered and run end to end; its
guards (output checks, lineage, its own) fail with one line naming the file."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

import mogaf.registry as reg
from mogaf import cli, stages
from mogaf.artefact import read_artefact, read_lineage, stage_inputs, write_artefact
from mogaf.errors import MogafError
from support import toy_stage
from support.paths import REPO


@pytest.fixture(autouse=True)
def _root_log_handlers(restore_root_logging):
    """Every test here may run a stage through run_stage (tests/conftest.py)."""


@pytest.fixture
def toy(monkeypatch):
    """The toy stage in the registry for one test (removed again after it)."""
    monkeypatch.setattr(reg, "STAGES", reg.STAGES)
    monkeypatch.setattr(reg, "BY_NAME", dict(reg.BY_NAME))
    return reg.register(toy_stage.SPEC)


@pytest.fixture
def source(tmp_path):
    return str(toy_stage.write_source(tmp_path / "scene.h5", [1.0, 2.0, 3.0]))


def _one_line(exc: pytest.ExceptionInfo) -> str:
    msg = str(exc.value)
    assert "\n" not in msg
    return msg


def test_toy_stage_runs_through_the_generic_runner(toy, source, tmp_path):
    out = tmp_path / "toy.h5"
    made = stages.run("toy", source=source, out=str(out), params={"scale": 2.0}, ratio="0.5", seed=7)
    assert made == out
    art = read_artefact(out, "toy")
    np.testing.assert_array_equal(art.data["values"], [2.0, 4.0, 6.0])
    assert art.data["seed"].tolist() == [7] and art.data["ratio"].tolist() == [0.5]
    assert not art.attrs["progress"]  # the spec's fixed keyword (the function defaults to True)
    # the runner opened the inputs' lineage: the artefact records what it was made from
    assert "ingest" in read_lineage(out).inputs


def test_toy_stage_python_entry_has_the_specs_signature(toy, source, tmp_path):
    import inspect

    entry = stages.toy  # derived from the spec, like mogaf.stages.refine
    assert list(inspect.signature(entry).parameters) == ["source", "out", "params", "ratio", "seed"]
    entry(source, str(tmp_path / "t.h5"), {"scale": 1.0}, "0.5", 1)
    assert (tmp_path / "t.h5").is_file()


def test_toy_guards_fail_with_one_line(toy, source, tmp_path):
    # the toy's own guard
    empty = str(toy_stage.write_source(tmp_path / "empty.h5", []))
    with pytest.raises(MogafError) as exc:
        stages.run("toy", source=empty, out=str(tmp_path / "a.h5"), params={"scale": 1.0}, ratio="0.5", seed=0)
    assert _one_line(exc) == f"{empty}: holds no values; the toy stage scales at least one"
    # the output checks every stage gets (mogaf.paths.check_outputs)
    with pytest.raises(MogafError) as exc:
        stages.run("toy", source=source, out=source, params={"scale": 1.0}, ratio="0.5", seed=0)
    assert _one_line(exc).startswith(f"{source}: is also an input of this stage; refusing to overwrite an input")
    # a required input left out
    with pytest.raises(MogafError, match="stage toy: no source given"):
        stages.run("toy", source=None, out=str(tmp_path / "b.h5"), params={"scale": 1.0}, ratio="0.5", seed=0)
    assert not any((tmp_path / n).exists() for n in ("a.h5", "b.h5"))


def test_lineage_guard_of_the_generic_runner(tmp_path, monkeypatch):
    """Inputs of two lineages are refused before the stage's function runs."""
    scene_a = toy_stage.write_source(tmp_path / "a" / "scene.h5", [1.0], digest="a")
    scene_b = toy_stage.write_source(tmp_path / "b" / "scene.h5", [1.0], digest="b")
    with stage_inputs(scene_b):
        split_b = write_artefact(tmp_path / "b" / "split.h5", "split", {}, config_digest="r")
    monkeypatch.setattr("mogaf.priors.stage.run_priors_stage", lambda *a, **k: pytest.fail("ran"))
    with pytest.raises(MogafError) as exc:
        stages.priors(str(scene_a), str(split_b), str(tmp_path / "p.h5"), {}, 0)
    assert "was made from another 'ingest' artefact" in _one_line(exc)


def test_toy_stage_cli(toy, source, tmp_path, monkeypatch, capsys):
    cfg = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    cfg.update(seed=3)
    configfile = tmp_path / "cfg.yaml"
    configfile.write_text(yaml.safe_dump(cfg))
    monkeypatch.chdir(REPO)
    # the config's `toy` section (a real stage adds it to the schema: docs/pipeline.md)
    monkeypatch.setattr(cli, "_config_for", lambda args: {**cfg, "toy": {"scale": 0.5}})
    out = tmp_path / "cli.h5"
    argv = ["toy", "--source-h5", source, "--out", str(out), "--ratio", "0.25", "--configfile", str(configfile)]
    assert cli.main(argv) == 0
    art = read_artefact(out, "toy")
    np.testing.assert_array_equal(art.data["values"], [0.5, 1.0, 1.5])
    assert art.data["seed"].tolist() == [3] and art.data["ratio"].tolist() == [0.25]
    assert "toy finished" in capsys.readouterr().err
    # a failing guard: one line on stderr, exit status 1
    empty = str(toy_stage.write_source(tmp_path / "empty.h5", []))
    with pytest.raises(SystemExit) as exc:
        cli.main(["toy", "--source-h5", empty, "--out", str(tmp_path / "x.h5"), "--ratio", "0.25"])
    assert exc.value.code == 1
    err = capsys.readouterr().err.strip()
    assert err == f"mogaf: error: {empty}: holds no values; the toy stage scales at least one"


def test_runner_refuses_a_wrapper_stage():
    with pytest.raises(TypeError, match="dedicated entry point: mogaf.stages.forecast_group"):
        stages.run("forecast_group")
