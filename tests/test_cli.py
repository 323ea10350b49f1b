"""`python -m mogaf ...`: bad configs, names and outputs fail with one line, and
every seeded stage gets the config's seed."""

from __future__ import annotations

import pytest
import yaml

from mogaf import cli, registry
from support.paths import REPO


@pytest.fixture
def in_repo(monkeypatch):
    monkeypatch.chdir(REPO)  # the CLI finds config/ relative to the working folder, as the workflow does


def _config(tmp_path, edit) -> str:
    cfg = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    edit(cfg)
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return str(path)


def _one_line_error(capsys, *argv: str) -> str:
    with pytest.raises(SystemExit) as exc:
        rc = cli.main(list(argv))
        raise SystemExit(rc)
    assert exc.value.code == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("mogaf: error: ") and "\n" not in err, err
    return err


WILDCARD_VALUES = {"ratio": "0.6", "method": "gcn", "group": "1"}


def _stage_args(tmp_path, command: str, configfile: str) -> list[str]:
    """Every path option of the stage's subcommand, and its wildcards (mogaf.registry)."""
    spec = registry.by_command(command)
    paths = {option: str(tmp_path / f"{option}.h5") for option in cli.stage_options(spec)}
    wildcards = [x for w in spec.wildcards if w not in cli.COMMON for x in (f"--{w}", WILDCARD_VALUES[w])]
    options = [x for option, path in paths.items() for x in (f"--{option}", path)]
    return [command, *options, *wildcards, "--configfile", configfile]


def test_config_the_schema_refuses_fails_with_one_line(in_repo, tmp_path, capsys):
    bad_seed = _config(tmp_path, lambda c: c.update(seed=-5))
    err = _one_line_error(capsys, *_stage_args(tmp_path, "priors", bad_seed))
    assert "cfg.yaml: seed:" in err
    no_forecast = _config(tmp_path, lambda c: c.pop("forecast"))  # stage settings may be left out, `forecast` not
    err = _one_line_error(capsys, *_stage_args(tmp_path, "priors", no_forecast))
    assert "cfg.yaml: top level:" in err and "'forecast' is a required property" in err


def test_unknown_synthetic_scene_names_the_choices(in_repo, tmp_path, capsys):
    err = _one_line_error(capsys, "synthesize", "--out", str(tmp_path / "s"), "--scene", "nope")
    assert "config/config.yaml: synthesize --scene must be a key of its `synthetic` section" in err
    assert "default" in err and "'nope'" in err


def test_output_that_cannot_be_written_names_it(in_repo, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    out = blocker / "scene"  # a folder inside a file
    err = _one_line_error(capsys, "synthesize", "--out", str(out), "--scene", "default")
    assert f"{out}: cannot be written" in err


def test_tables_refuse_a_missing_metrics_file(in_repo, tmp_path, capsys):
    err = _one_line_error(capsys, "tables", str(tmp_path / "nope.json"), "--out-dir", str(tmp_path / "t"))
    assert "nope.json: no such metrics file" in err
    assert not (tmp_path / "t").exists()


@pytest.mark.parametrize("command", sorted(cli.SEEDED))
def test_seeded_stages_get_the_config_seed(in_repo, tmp_path, monkeypatch, command):
    seen = {}
    monkeypatch.setattr(cli.stages, "run_stage", lambda fn, log, threads=None, **kw: seen.update(kw))
    configfile = _config(tmp_path, lambda c: c.update(seed=7))
    assert cli.main(_stage_args(tmp_path, command, configfile)) == 0
    assert seen["seed"] == 7


@pytest.mark.parametrize("command", sorted(cli.DEVICE))
def test_device_stages_get_the_config_device(in_repo, tmp_path, monkeypatch, command):
    seen = {}
    monkeypatch.setattr(cli.stages, "run_stage", lambda fn, log, threads=None, **kw: seen.update(kw))
    configfile = _config(tmp_path, lambda c: c.update(device="cpu"))
    assert cli.main(_stage_args(tmp_path, command, configfile)) == 0
    assert seen["device"] == "cpu"
    # only the training stages resume from a checkpoint
    assert ("checkpoint" in seen) == (command in cli.CHECKPOINT)


def test_every_stage_using_the_gpu_takes_the_device():
    assert {"recon", "refine", "forecast-group"} <= cli.DEVICE and {"recon", "refine"} == cli.CHECKPOINT


def test_every_stage_using_randomness_is_seeded():
    # priors (track sampling), recon, group (PCA, priority order), refine and the forecasters draw random numbers
    assert {"priors", "recon", "group", "refine", "forecast-group", "forecast"} <= cli.SEEDED


@pytest.mark.parametrize("command", sorted(c for c, s in registry.commands().items() if s.name not in cli.SPECIAL))
def test_every_stage_subcommand_calls_its_entry(in_repo, tmp_path, monkeypatch, command):
    """Each subcommand is derived from its spec: the stage's entry gets its
    paths, wildcards and config section (synthesize and ingest, whose settings
    are not one section: the tests above and tests/test_bad_inputs.py)."""
    spec = registry.by_command(command)
    seen = {}
    monkeypatch.setattr(cli.stages, "run_stage", lambda fn, log, threads=None, **kw: seen.update(kw, fn=fn))
    configfile = _config(tmp_path, lambda c: None)
    assert cli.main(_stage_args(tmp_path, command, configfile)) == 0
    assert seen.pop("fn") is cli.stages.entry(spec.name)
    for option, argument in cli.stage_options(spec).items():
        if argument in (i.argument for i in spec.inputs if i.many):
            continue
        assert seen.pop(argument) == str(tmp_path / f"{option}.h5")
    for w in spec.wildcards:
        assert seen.pop(w) == WILDCARD_VALUES[w]
    if spec.settings:
        assert isinstance(seen.pop("params"), dict)


def test_forecast_merge_subcommand(in_repo, tmp_path, monkeypatch):
    seen = {}
    monkeypatch.setattr(cli.stages, "run_stage", lambda fn, log, threads=None, **kw: seen.update(kw, fn=fn))
    args = ["forecast", "--model-h5", "m.h5", "--groups-h5", "g.h5", "--split-h5", "s.h5", "--out", "f.h5"]
    assert cli.main([*args, "--method", "gcn", "--parts", "a.h5", "b.h5", "--threads", "1"]) == 0
    assert seen["fn"] is cli.stages.forecast_merge and seen["parts"] == ["a.h5", "b.h5"] and seen["method"] == "gcn"
    # the device and threads a trained method computes with under forecast.jobs: per_method
    assert seen["params"]["methods"] and seen["device"] == "auto" and seen["job_threads"] == 1


def test_grouping_quality_gets_its_config_section(in_repo, tmp_path, monkeypatch):
    seen = {}
    monkeypatch.setattr(cli.stages, "run_stage", lambda fn, log, threads=None, **kw: seen.update(kw, fn=fn))
    configfile = _config(tmp_path, lambda c: c["grouping_quality"].update(pixels="all"))
    assert cli.main(_stage_args(tmp_path, "grouping-quality", configfile)) == 0
    assert seen["fn"] is cli.stages.grouping_quality and seen["params"]["pixels"] == "all"
    assert seen["grouped_model"] == str(tmp_path / "grouped-model-h5.h5")


def test_reconstruction_quality_gets_its_config_section(in_repo, tmp_path, monkeypatch):
    seen = {}
    monkeypatch.setattr(cli.stages, "run_stage", lambda fn, log, threads=None, **kw: seen.update(kw, fn=fn))
    configfile = _config(tmp_path, lambda c: c["reconstruction_quality"].update(max_frames=3))
    assert cli.main(_stage_args(tmp_path, "reconstruction-quality", configfile)) == 0
    assert seen["fn"] is cli.stages.reconstruction_quality
    assert seen["params"] == {"max_frames": 3, "tracking_neighbors": 4}
    assert seen["model"] == str(tmp_path / "model-h5.h5")


def test_evaluate_reads_the_quality_files(in_repo, tmp_path, monkeypatch):
    seen = {}
    monkeypatch.setattr(cli.stages, "run_stage", lambda fn, log, threads=None, **kw: seen.update(kw, fn=fn))
    args = [
        "evaluate",
        "--scene-h5",
        "s.h5",
        "--split-h5",
        "p.h5",
        "--model-h5",
        "m.h5",
        "--groups-h5",
        "g.h5",
        "--reconstruction-quality-h5",
        "rq.h5",
        "--grouping-quality-h5",
        "q.h5",
        "--out",
        "metrics.json",
        "--renders",
        "r",
        "--forecast",
        "frozen=f.h5",
        "--ratio",
        "0.6",
    ]
    assert cli.main(args) == 0
    assert seen["fn"] is cli.stages.evaluate and seen["grouping_quality"] == "q.h5" and seen["groups"] == "g.h5"
    assert seen["reconstruction_quality"] == "rq.h5"
    assert seen["forecasts"] == {"frozen": "f.h5"}
