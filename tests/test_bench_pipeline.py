"""`python -m mogaf.bench pipeline`: budgets, per-job rows and the training loops' breakdown from a results folder."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mogaf.artefact import write_artefact
from mogaf.bench import pipeline

HEADER = "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"


def _job(folder, name, wall, cpu, own=None):
    (folder / "benchmarks").mkdir(parents=True, exist_ok=True)
    (folder / "logs").mkdir(parents=True, exist_ok=True)
    (folder / "benchmarks" / f"{name}.tsv").write_text(HEADER + f"{wall}\t0:00:01\t1\t1\t1\t1\t0\t0\t50\t{cpu}\n")
    if own is not None:
        (folder / "logs" / f"{name}.log").write_text(
            f"2026-11-26 08:00:00,000 INFO mogaf: {name} finished in {own} s, process CPU {own - 1.0} s\n"
        )


# (benchmark file stem, wall s, Snakemake's sampled CPU s): the demo's job names
JOBS = [
    ("priors", 1.0, 0.5),
    ("group", 4.0, 3.5),
    ("rigid_init", 3.0, 2.0),
    ("grouping_quality", 2.0, 2.0),
    ("reconstruction_quality_refined", 2.0, 2.0),
    ("forecast_mogaf_group0", 9.0, 8.0),
    ("forecast_mogaf_group1", 12.0, 11.0),
    ("forecast_mogaf_paper_group1", 8.0, 7.0),
    ("forecast_mogaf", 3.0, 2.5),
    ("forecast_gcn_group0", 14.0, 13.0),
    ("forecast_gcn", 3.0, 2.5),
    ("forecast_constant_velocity", 3.0, 2.5),
    ("evaluate", 18.0, 30.0),
]


@pytest.fixture()
def results(tmp_path):
    ratio = tmp_path / "results" / "synthetic" / "default" / "ratio0.6"
    _job(ratio, "recon", 50.0, 45.0, own=48.0)
    _job(ratio, "refine", 30.0, 25.0, own=28.5)
    for name, wall, cpu in JOBS:
        _job(ratio, name, wall, cpu)
    _job(ratio / "ablation" / "rt_fast_quick", "recon", 20.0, 19.0)
    breakdown = {"init": 3.0, "rasterizer_forward": 10.0, "rasterizer_backward": 12.0, "steps_total": 40.0}
    write_artefact(
        ratio / "recon.h5", "recon", {"x": np.zeros(1)}, config_digest="0", attrs={"time_breakdown_s": breakdown}
    )
    return ratio


def test_budgets_take_the_slowest_job_or_the_sum(results):
    jobs = pipeline.collect(results)
    rows = {r["row"]: r for r in pipeline.budget_rows(jobs, snakemake_s=200.0)}
    assert rows["recon"]["wall_s"] == 50.0 and rows["recon"]["within"]  # the sweep's recon is not a row's job
    assert rows["refine"]["wall_s"] == 30.0 and not rows["refine"]["within"]
    quality = rows["rigid_init + group + quality stages"]
    assert (quality["jobs"], quality["wall_s"], quality["within"]) == (4, 11.0, False)  # a sum: over its 10 s
    assert rows["baseline forecast job"]["jobs"] == 3  # the GCN's group job and merge, constant velocity
    assert not any("priors" in r["worst"] for r in rows.values())
    mogaf = rows["MoGaF forecast job"]
    assert (mogaf["jobs"], mogaf["wall_s"], mogaf["worst"], mogaf["within"]) == (
        4,
        12.0,
        "forecast_mogaf_group1",
        False,
    )
    assert rows["baseline forecast job"]["within"] and rows["evaluate"]["within"]
    assert rows["Snakemake run (whole demo)"]["wall_s"] == 200.0 and not rows["Snakemake run (whole demo)"]["within"]


def test_jobs_carry_their_own_time_and_breakdown(results):
    jobs = {(j.name, j.sweep): j for j in pipeline.collect(results)}
    recon = jobs[("recon", "")]
    # CPU time from the log's own figure, not Snakemake's sampled cpu_time (45.0)
    assert recon.own_s == 48.0 and recon.start_s == 2.0 and recon.cpu_s == 47.0
    assert jobs[("group", "")].cpu_s == 3.5  # no log line: the sampled figure
    assert recon.detail["rasterizer_backward"] == 12.0
    assert jobs[("recon", "rt_fast_quick")].detail == {}
    table = pipeline.render(list(jobs.values()), pipeline.budget_rows(list(jobs.values()), None))
    assert "| recon | 1 | 50.0 | 47.0 | 60 | yes |  |" in table
    # the rasterizer's backward and forward shares of the steps (the artefact keeps its keys sorted)
    assert "| recon |  | 40.0 | 30 % | 25 % |" in table


def test_a_folder_without_benchmarks_is_one_clear_error(tmp_path, capsys):
    assert pipeline.main(["--results", str(tmp_path)]) == 2
    assert "no benchmarks/ folder" in capsys.readouterr().err


def test_schedule_bound_is_the_longer_of_the_critical_path_and_the_cpu_per_core(results):
    jobs = pipeline.collect(results)
    bound = pipeline.schedule_bound(jobs, cores=2)
    # priors 1 -> recon 50 -> group 4 -> rigid_init 3 -> refine 30 -> the GCN's group job 14 and merge 3 -> evaluate 18
    assert bound["critical_path"] == [
        ("priors", ""),
        ("recon", ""),
        ("group", ""),
        ("rigid_init", ""),
        ("refine", ""),
        ("forecast_gcn_group0", ""),
        ("forecast_gcn", ""),
        ("evaluate", ""),
    ]
    assert bound["critical_path_s"] == pytest.approx(123.0)
    # CPU from the logs where they say it (recon 47, refine 27.5), else Snakemake's samples; the sweep's recon too
    cpu = 47.0 + 27.5 + sum(c for _, _, c in JOBS) + 19.0
    assert bound["cpu_per_core_s"] == pytest.approx(cpu / 2)
    assert bound["bound_s"] == pytest.approx(max(123.0, cpu / 2))
    one_core = pipeline.schedule_bound(jobs, cores=1)
    assert one_core["bound_s"] == pytest.approx(cpu) and cpu > 123.0


def test_a_sweep_waits_for_the_runs_shared_jobs(results):
    """The sweep's recon has no priors job of its own: it waits for the run's."""
    jobs = pipeline.collect(results)
    sweep_recon = next(j for j in jobs if j.sweep and j.name == "recon")
    assert [(j.name, j.sweep) for j in pipeline._needs(sweep_recon, jobs)] == [("priors", "")]


def test_bad_flags_and_an_empty_benchmarks_folder_fail_before_any_work(results, tmp_path, capsys):
    (tmp_path / "empty" / "benchmarks").mkdir(parents=True)
    assert pipeline.main(["--results", str(tmp_path / "empty")]) == 2
    assert "its benchmarks/ folder holds no job's .tsv" in capsys.readouterr().err
    for argv, words in (
        (["--cores", "0"], "--cores must be at least 1, got 0"),
        (["--snakemake-seconds", "nan"], "--snakemake-seconds must be a finite number >= 0, got nan"),
        (["--run", "--snakemake", str(tmp_path / "nosuch")], "no such executable"),
    ):
        with pytest.raises(SystemExit) as exc:
            pipeline.main(["--results", str(results), *argv])
        assert exc.value.code == 2 and words in capsys.readouterr().err
    folder = tmp_path / "rows.json"
    folder.mkdir()
    assert pipeline.main(["--results", str(results), "--json", str(folder)]) == 2
    assert f"{folder}: is an existing directory" in capsys.readouterr().err


def test_the_json_rows_are_written_whole(results, tmp_path, monkeypatch):
    monkeypatch.setattr(pipeline, "import_seconds", lambda: {"python": 0.01})
    out = tmp_path / "rows.json"
    assert pipeline.main(["--results", str(results), "--json", str(out), "--snakemake-seconds", "300"]) == 0
    assert json.loads(out.read_text())["snakemake_s"] == 300.0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results", "rows.json"]  # no temporary beside it
