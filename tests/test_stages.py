"""mogaf.stages: every stage declares the artefacts it reads, so inputs of
another lineage are refused before any work (mogaf.artefact.stage_inputs)."""

from __future__ import annotations

import pytest

from mogaf import stages
from mogaf.artefact import read_lineage, stage_inputs, write_artefact
from mogaf.errors import MogafError


def _chain(folder, recon_digest="recon"):
    """scene -> split -> priors -> recon -> groups, written as stages would write them."""
    folder.mkdir(parents=True, exist_ok=True)
    scene = write_artefact(folder / "scene.h5", "ingest", {}, config_digest="scene")
    with stage_inputs(scene):
        split = write_artefact(folder / "split.h5", "split", {}, config_digest="r0.6")
    with stage_inputs(scene, split):
        priors = write_artefact(folder / "priors.h5", "priors", {}, config_digest="priors")
    with stage_inputs(scene, split, priors):
        recon = write_artefact(folder / "recon.h5", "recon", {}, config_digest=recon_digest)
    with stage_inputs(recon, priors, scene):
        groups = write_artefact(folder / "groups.h5", "group", {}, config_digest="groups")
    return {"scene": scene, "split": split, "priors": priors, "recon": recon, "groups": groups}


@pytest.fixture
def never_run(monkeypatch):
    """Stage bodies that fail the test if the lineage check lets them run."""
    import mogaf.evaluate.stage
    import mogaf.forecast.stage
    import mogaf.grouping.quality
    import mogaf.reconstruction_quality.stage
    import mogaf.refine.stage

    def body(*args, **kwargs):
        raise AssertionError("the stage ran on inputs of another lineage")

    for module, name in (
        (mogaf.refine.stage, "run_refine_stage"),
        (mogaf.forecast.stage, "run_forecast_group"),
        (mogaf.grouping.quality, "run_grouping_quality_stage"),
        (mogaf.evaluate.stage, "run_evaluate_stage"),
        (mogaf.reconstruction_quality.stage, "run_reconstruction_quality_stage"),
    ):
        monkeypatch.setattr(module, name, body)


def test_stages_refuse_inputs_of_another_lineage(tmp_path, never_run):
    a = _chain(tmp_path / "a")
    b = _chain(tmp_path / "b", recon_digest="recon-other-budget")  # e.g. a run-time sweep variant's reconstruction
    assert read_lineage(a["recon"]).digest != read_lineage(b["recon"]).digest
    with pytest.raises(MogafError, match=r"a/groups\.h5: was made from another 'recon' artefact than .*b/recon\.h5"):
        stages.refine(
            model=str(b["recon"]),
            groups=str(a["groups"]),
            rigid=None,
            priors=str(a["priors"]),
            scene=str(a["scene"]),
            split=str(a["split"]),
            out=str(tmp_path / "r.h5"),
            params={},
            seed=0,
        )
    with pytest.raises(MogafError, match=r"groups\.h5: was made from another 'recon' artefact"):
        stages.forecast_group(
            model=str(b["recon"]),
            groups=str(a["groups"]),
            split=str(a["split"]),
            out=str(tmp_path / "f.h5"),
            params={},
            method="frozen",
            group="1",
            seed=0,
        )
    with stage_inputs(a["recon"], a["groups"], a["split"]):
        forecast = write_artefact(tmp_path / "frozen.h5", "forecast", {}, config_digest="frozen")
    with stage_inputs(b["recon"], b["groups"], b["scene"], b["split"]):
        quality = write_artefact(tmp_path / "grouping_quality.h5", "grouping_quality", {}, config_digest="q")
    with stage_inputs(b["recon"], b["scene"], b["split"]):
        model_quality = write_artefact(tmp_path / "b_quality.h5", "reconstruction_quality", {}, config_digest="m")
    with stage_inputs(a["recon"], a["scene"], a["split"]):
        a_model_quality = write_artefact(tmp_path / "a_quality.h5", "reconstruction_quality", {}, config_digest="m")
    with pytest.raises(MogafError, match=r"a/groups\.h5: was made from another 'recon' artefact"):
        stages.grouping_quality(
            grouped_model=str(b["recon"]),
            groups=str(a["groups"]),
            scene=str(a["scene"]),
            split=str(a["split"]),
            out=str(tmp_path / "q.h5"),
            params={},
        )
    with pytest.raises(MogafError, match=r"frozen\.h5: was made from another 'recon' artefact"):
        stages.evaluate(
            scene=str(a["scene"]),
            split=str(a["split"]),
            model=str(b["recon"]),
            groups=str(b["groups"]),
            reconstruction_quality=str(model_quality),
            grouping_quality=str(quality),
            forecasts={"frozen": str(forecast)},
            benchmarks={},
            out_metrics=str(tmp_path / "m.json"),
            out_renders=str(tmp_path / "renders"),
            params={},
            variant="default",
            ids={},
        )
    with stage_inputs(a["recon"], a["groups"], a["scene"], a["split"]):
        a_grouping_quality = write_artefact(
            tmp_path / "a_grouping_quality.h5", "grouping_quality", {}, config_digest="q"
        )
    # the grouping's quality of other groups than the forecasts' (same reconstruction: e.g. Gaga-4D's)
    with stage_inputs(a["recon"], a["priors"], a["scene"]):
        other_groups = write_artefact(tmp_path / "gaga" / "groups.h5", "group", {}, config_digest="gaga4d")
    with stage_inputs(a["recon"], other_groups, a["scene"], a["split"]):
        other_quality = write_artefact(
            tmp_path / "gaga" / "grouping_quality.h5", "grouping_quality", {}, config_digest="q"
        )
    with pytest.raises(
        MogafError, match=r"gaga/grouping_quality\.h5: was made from another 'group' artefact than .*a/groups\.h5"
    ):
        stages.evaluate(
            scene=str(a["scene"]),
            split=str(a["split"]),
            model=str(a["recon"]),
            groups=str(a["groups"]),
            reconstruction_quality=str(a_model_quality),
            grouping_quality=str(other_quality),
            forecasts={"frozen": str(forecast)},
            benchmarks={},
            out_metrics=str(tmp_path / "m.json"),
            out_renders=str(tmp_path / "renders"),
            params={},
            variant="default",
            ids={},
        )
    # the reconstruction quality of another model than the forecasts start from
    with pytest.raises(MogafError, match=r"b_quality\.h5: was made from another 'recon' artefact than .*a/recon\.h5"):
        stages.evaluate(
            scene=str(a["scene"]),
            split=str(a["split"]),
            model=str(a["recon"]),
            groups=str(a["groups"]),
            reconstruction_quality=str(model_quality),
            grouping_quality=str(a_grouping_quality),
            forecasts={"frozen": str(forecast)},
            benchmarks={},
            out_metrics=str(tmp_path / "m.json"),
            out_renders=str(tmp_path / "renders"),
            params={},
            variant="default",
            ids={},
        )
    # one lineage, yet a measurement of recon.h5 where the forecasts start from refined.h5
    with stage_inputs(a["recon"], a["groups"], a["scene"], a["split"]):
        refined = write_artefact(tmp_path / "refined.h5", "refine", {}, config_digest="refine")
    with stage_inputs(refined, a["groups"], a["split"]):
        forecast_of_refined = write_artefact(tmp_path / "frozen_refined.h5", "forecast", {}, config_digest="frozen")
    with pytest.raises(
        MogafError,
        match=r"a_quality\.h5: was not made from .*refined\.h5 \(a 'refine' artefact; it was "
        r"made from 'ingest', 'recon', 'split'\)",
    ):
        stages.evaluate(
            scene=str(a["scene"]),
            split=str(a["split"]),
            model=str(refined),
            groups=str(a["groups"]),
            reconstruction_quality=str(a_model_quality),
            grouping_quality=str(a_grouping_quality),
            forecasts={"frozen": str(forecast_of_refined)},
            benchmarks={},
            out_metrics=str(tmp_path / "m.json"),
            out_renders=str(tmp_path / "renders"),
            params={},
            variant="default",
            ids={},
        )
    assert not any((tmp_path / name).exists() for name in ("r.h5", "q.h5", "m.json"))


def test_a_stage_that_sets_no_torch_threads_still_refuses_a_bad_count_and_never_imports_torch():
    """run_stage's threads for a stage whose registry entry says torch_threads:
    False (under Snakemake and from the command line alike): a bad count is
    the same one-line error, a good one leaves torch alone (not imported)."""
    import subprocess
    import sys

    from support.paths import REPO

    code = (
        "import sys\n"
        "from mogaf.errors import MogafError\n"
        "from mogaf.stages import set_threads\n"
        "set_threads(2, torch_threads=False)\n"
        "try:\n"
        "    set_threads(-3, torch_threads=False)\n"
        "except MogafError as exc:\n"
        "    print(exc)\n"
        "print('torch' in sys.modules)\n"
        "set_threads(1)\n"
        "import torch\n"
        "print(torch.get_num_threads())"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stdout.split("\n")[:3] == ["threads must be a positive integer, got -3", "False", "1"]
