"""`python -m mogaf.bench forecast` (mogaf.bench.forecast)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mogaf.bench import forecast as bench
from mogaf.errors import MogafError
from mogaf.forecast.synthetic import rigid_box, static_cloud


def test_evaluate_trajectories_scores_references():
    traj = static_cloud(20, 30)
    rows = bench.evaluate_trajectories(traj, 0.6, methods=("frozen", "constant_velocity"))
    assert [r["method"] for r in rows] == ["frozen", "constant_velocity"]
    for r in rows:
        assert r["observed_frames"] == 18 and r["forecast_frames"] == 12
        assert r["epe"] < 1e-12 and r["rot_err_deg"] < 1e-6


def test_frozen_error_grows_step_by_step_on_a_moving_box():
    traj = rigid_box(40, 30)
    (row,) = bench.evaluate_trajectories(traj, 0.6, methods=("frozen",))
    steps = np.asarray(row["epe_per_step"])
    assert steps.shape == (12,) and np.all(steps > 0)
    assert np.isclose(steps.mean(), row["epe"], atol=1e-5)  # the mean EPE is the mean over steps
    assert steps[-1] > steps[0]  # a held pose falls further behind a moving box


def test_split_rejects_bad_input():
    with pytest.raises(MogafError, match="shape"):
        bench.split(np.zeros((3, 10, 6)), 0.6)
    with pytest.raises(MogafError, match="ratio"):
        bench.split(np.zeros((3, 10, 7)), 1.0)


def test_cli_procedural_npz_and_source(tmp_path, capsys, monkeypatch):
    (tmp_path / "my_gt_source.py").write_text(
        "from mogaf.forecast.synthetic import rigid_box\ndef tiny():\n    return {'tiny': rigid_box(8, 16)}\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    npz = tmp_path / "gt.npz"
    np.savez(npz, scene_group_0=rigid_box(15, 20))
    out_json = tmp_path / "rows.json"
    rc = bench.main(
        [
            "--sets",
            "static",
            "--gaussians",
            "10",
            "--frames",
            "20",
            "--npz",
            str(npz),
            "--source",
            "my_gt_source:tiny",
            "--methods",
            "frozen,constant_velocity,mogaf",
            "--params",
            '{"mogaf": {"iterations": 3, "batch_size": 8}}',
            "--json",
            str(out_json),
        ]
    )
    assert rc == 0
    table = capsys.readouterr().out
    for name in ("static", "scene_group_0", "tiny"):
        assert name in table
    rows = json.loads(out_json.read_text())["rows"]
    assert len(rows) == 3 * 2 * 3
    assert all(np.isfinite(r["epe"]) for r in rows)


def test_cli_errors_are_one_line(capsys):
    assert bench.main(["--sets", "nope"]) == 1
    assert bench.main(["--sets", "static", "--methods", "lstm"]) == 1
    err = capsys.readouterr().err
    assert "unknown set 'nope'" in err and "unknown method(s) lstm" in err


def test_cli_resume_keeps_finished_rows_and_only_filters(tmp_path, capsys):
    out_json = tmp_path / "rows.json"
    base = [
        "--sets",
        "static,rigid_box",
        "--only",
        "stat*",
        "--gaussians",
        "6",
        "--frames",
        "20",
        "--ratios",
        "0.6",
        "--json",
        str(out_json),
    ]
    assert bench.main(base + ["--methods", "frozen"]) == 0
    doc = json.loads(out_json.read_text())
    assert [(r["set"], r["method"]) for r in doc["rows"]] == [("static", "frozen")]
    doc["rows"][0]["epe"] = 123.0  # a kept row must come back unchanged, not recomputed
    out_json.write_text(json.dumps(doc))
    assert bench.main(base + ["--methods", "frozen,constant_velocity", "--resume"]) == 0
    rows = json.loads(out_json.read_text())["rows"]
    assert [(r["method"], r["epe"]) for r in rows][0] == ("frozen", 123.0)
    assert [r["method"] for r in rows] == ["frozen", "constant_velocity"] and rows[1]["epe"] < 1e-9
    capsys.readouterr()
    assert bench.main(base + ["--methods", "frozen", "--resume", "--seed", "1"]) == 1
    assert "written with another seed" in capsys.readouterr().err
    doc = json.loads(out_json.read_text())
    assert doc["device"] == "cpu"
    # rows from another device do not mix with these ("auto" is resolved before comparing)
    out_json.write_text(json.dumps({**doc, "device": "cuda"}))
    assert bench.main(base + ["--methods", "frozen", "--resume", "--device", "cpu"]) == 1
    assert "written with another device ('cuda')" in capsys.readouterr().err
    # a file from before --device was recorded counts as a CPU run
    del doc["device"]
    out_json.write_text(json.dumps(doc))
    assert bench.main(base + ["--methods", "frozen", "--resume"]) == 0
    # rows of other code (or of code before digests were recorded) are never kept beside this code's
    assert doc["code"] == bench.code_digest()
    other = "its rows were computed by other mogaf code"
    for older, why in (
        ({**doc, "code": "0" * 16}, f"{other} (code '0000000000000000'; this is {doc['code']})"),
        ({k: v for k, v in doc.items() if k != "code"}, f"{other} (code from before digests were recorded;"),
    ):
        out_json.write_text(json.dumps(older))
        assert bench.main(base + ["--methods", "frozen", "--resume"]) == 1
        assert why in capsys.readouterr().err
    out_json.write_text(json.dumps({**doc, "code": "a|b"}))  # a hand-edited digest breaks no results table
    with pytest.raises(MogafError, match=r"has code 'a\|b', not a digest of 16 hex digits"):
        bench.read_rows(out_json)
    out_json.write_text(json.dumps(doc))
    assert bench.main(base + ["--methods", "frozen"]) == 1  # no silent overwrite without --resume
    assert "exists; pass --resume" in capsys.readouterr().err
    longer = [a if a != "20" else "30" for a in base]  # other trajectories under the same set name
    assert bench.main(longer + ["--methods", "frozen", "--resume"]) == 1
    assert "was scored on 6 Gaussians x 12 observed frames" in capsys.readouterr().err


def _bench_file(path, budget, rows):
    base = {"gaussians": 4, "observed_frames": 12, "rot_err_deg": 0.0, "flags": []}
    doc = {"budget": budget, "params": {}, "seed": 0, "rows": [{**base, **r} for r in rows]}
    path.write_text(json.dumps(doc))
    return path


def test_comparison_table_merges_files_and_refuses_disagreement(tmp_path, capsys):
    box = {"set": "default/box", "ratio": 0.6}
    cpu = _bench_file(
        tmp_path / "cpu.json",
        "cpu",
        [
            {**box, "method": "frozen", "epe": 0.2, "train_s": 0.0},
            {**box, "method": "gcn", "epe": 0.5, "train_s": 30.0},
        ],
    )
    paper = _bench_file(
        tmp_path / "paper.json",
        "paper",
        [
            {**box, "method": "gcn", "epe": 0.1, "train_s": 3600.0, "flags": ["window_clipped"]},
            {**box, "method": "frozen", "epe": 0.2, "train_s": 0.0},  # the same row twice is fine
            {"set": "default/box", "ratio": 0.8, "method": "frozen", "epe": 0.3, "train_s": 0.0},
        ],
    )
    assert bench.main(["--from-json", str(cpu), "--from-json", str(paper)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "| set | ratio | gcn EPE | gcn* EPE | frozen EPE | gcn train s | gcn* train s |"
    assert lines[2] == "| default/box | 0.60 | **0.1000 (window_clipped)** | 0.5000 | 0.2000 | 3,600 | 30 |"
    assert lines[3] == "| default/box | 0.80 | – | – | **0.3000** | – | – |"
    assert "shortened training" in lines[-1] and "gcn" in lines[-1]

    other = _bench_file(tmp_path / "other.json", "paper", [{**box, "method": "frozen", "epe": 0.25, "train_s": 0.0}])
    with pytest.raises(
        MogafError, match=r"other\.json: default/box ratio 0\.6 frozen has EPE 0\.25, .*cpu\.json has 0\.2"
    ):
        bench.comparison_table([cpu, other])
    longer = tmp_path / "longer.json"
    longer.write_text(
        json.dumps(
            {
                "budget": "paper",
                "rows": [{**box, "method": "ode", "epe": 0.1, "train_s": 1.0, "gaussians": 4, "observed_frames": 13}],
            }
        )
    )
    with pytest.raises(MogafError, match="scored on other trajectories"):
        bench.comparison_table([cpu, longer])
    broken = tmp_path / "broken.json"
    broken.write_text(json.dumps({"rows": [{"set": "x", "ratio": 0.6, "method": "frozen"}]}))
    assert bench.main(["--from-json", str(broken)]) == 1
    assert "broken.json: row 0 has no epe, train_s" in capsys.readouterr().err
    broken.write_text(json.dumps({"rows": [{"set": "x", "ratio": "abc", "method": "frozen", "epe": 1, "train_s": 0}]}))
    assert bench.main(["--from-json", str(broken)]) == 1
    assert "broken.json: row 0 has ratio 'abc', not a number" in capsys.readouterr().err


def test_a_step_budget_is_its_own_column_and_only_keeps_the_named_sets(tmp_path, capsys):
    box, cloth = {"set": "default/box", "ratio": 0.6}, {"set": "default/cloth", "ratio": 0.6}
    paper = _bench_file(
        tmp_path / "paper.json",
        "paper",
        [
            {**box, "method": "ode", "epe": 0.3, "train_s": 300.0},
            {**cloth, "method": "ode", "epe": 0.27, "train_s": 1.0},
        ],
    )
    steps = tmp_path / "steps.json"
    doc = json.loads(_bench_file(steps, "paper", [{**box, "method": "ode", "epe": 0.2, "train_s": 1700.0}]).read_text())
    steps.write_text(json.dumps({**doc, "params": {"ode": {"num_threads": 1, "steps": 800}}}))
    # the same (set, ratio, method) at two budgets: two columns, not a disagreement
    assert bench.main(["--from-json", str(paper), "--from-json", str(steps), "--only", "*/box"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "| set | ratio | ode EPE | ode@800 EPE | ode train s | ode@800 train s |"
    assert lines[2] == "| default/box | 0.60 | 0.3000 | **0.2000** | 300 | 1,700 |"
    assert len([x for x in lines if x.startswith("| default/")]) == 1  # cloth left out by --only
    assert lines[-1].startswith("@N: trained for") and lines[-1].endswith("ode@800")
    assert bench.column_name({"budget": "cpu", "params": {"ode": {"steps": 0}}}, "ode") == "ode*"
    assert bench.column_name({"budget": "paper", "params": {"mogaf": {"steps": 5}}}, "mogaf") == "mogaf"


def _marked_block(page, tag):
    """The text of docs between <!-- tag --> and <!-- /tag --> lines."""
    start, end = f"<!-- {tag} -->\n", f"\n<!-- /{tag} -->"
    return page[page.index(start) + len(start) : page.index(end)]


def test_docs_forecast_tables_are_made_from_the_committed_rows(monkeypatch):
    from pathlib import Path

    from support.paths import REPO

    monkeypatch.chdir(REPO)  # the page names the files as the generator finds them: relative to the checkout
    bench_dir = Path("results") / "bench"
    page = (REPO / "docs" / "results.md").read_text()
    files = [bench_dir / f"forecast_gt_{name}.json" for name in ("defaults", "paper_gcn", "paper_ode")]
    assert _marked_block(page, "forecast-gt-table") == bench.markdown_report(files)
    # the latent ODE at 800 steps beside its paper budget, on the rows it ran
    files = [bench_dir / f"forecast_gt_{name}.json" for name in ("defaults", "paper_ode")]
    files += sorted(bench_dir.glob("forecast_gt_steps_ode_*.json"))
    assert _marked_block(page, "forecast-gt-ode-steps-table") == bench.markdown_report(
        files, only=["default/box", "default/sphere", "default/cloth", "hard/box", "hard/sphere", "hard/cloth"]
    )


def test_summary_counts_wins_over_the_references(tmp_path):
    rows = []
    for i, (a, cv, fr) in enumerate([(0.1, 0.2, 0.3), (0.3, 0.2, 0.4), (0.1, 0.5, 0.05)]):
        key = {"set": f"s{i}", "ratio": 0.6, "epe_per_step": [0.0, 0.1]}
        rows += [
            {**key, "method": "mogaf", "epe": a, "train_s": 1.0},
            {**key, "method": "constant_velocity", "epe": cv, "train_s": 0.0},
            {**key, "method": "frozen", "epe": fr, "train_s": 0.0},
        ]
    path = _bench_file(tmp_path / "d.json", "cpu", rows)
    summary = bench.summary_table([path]).splitlines()
    assert summary[2] == "| mogaf | **0.1667** | 2 of 3 (67 %) | 2 of 3 (67 %) |"
    assert summary[3] == "| constant_velocity | 0.3000 | – | 2 of 3 (67 %) |"
    steps = bench.per_step_table([path]).splitlines()
    assert steps[2] == "| s0 | 0.60 | 1 / 2 | 0.0000 / 0.1000 | 0.0000 / 0.1000 | 0.0000 / 0.1000 |"


def test_cli_flags_are_checked_before_any_training(tmp_path, capsys):
    for argv, words in (
        (["--ratios", "abc"], "--ratios takes numbers in (0, 1)"),
        (["--ratios", "0.6,1.5"], "--ratios takes numbers in (0, 1)"),
        (["--params", "[1]"], "--params must be a JSON object {method: {param: value}}"),
        (["--params", '{"ode": 3}'], "--params must be a JSON object"),
    ):
        assert bench.main(["--sets", "static", *argv]) == 1
        assert words in capsys.readouterr().err
    text = tmp_path / "sets.npz"
    text.write_text("not an archive")
    assert bench.main(["--sets", "none", "--npz", str(text)]) == 1
    assert f"{text}: cannot read as .npz" in capsys.readouterr().err
    (tmp_path / "afile").write_text("")
    assert bench.main(["--sets", "static", "--json", str(tmp_path / "afile" / "rows.json")]) == 1
    assert "rows.json: cannot be written" in capsys.readouterr().err


def test_the_synthetic_sources_cache_is_keyed_by_the_generators_code(tmp_path, monkeypatch):
    """A scene cached by other generator code is generated again: the cache
    folder carries code_digest of mogaf/synth, which a changed .py file changes."""
    from mogaf.bench import _forecast_sources as sources

    (tmp_path / "generate.py").write_text("A = 1\n")
    (tmp_path / "notes.txt").write_text("not code")
    before = sources.code_digest(tmp_path)
    (tmp_path / "notes.txt").write_text("still not code")
    assert sources.code_digest(tmp_path) == before
    (tmp_path / "generate.py").write_text("A = 2\n")
    assert sources.code_digest(tmp_path) != before
    folders = []
    monkeypatch.setattr(sources, "cache_dir", lambda *parts: folders.append(parts) or tmp_path / "cache")
    monkeypatch.setattr("mogaf.synth.generate.generate_scene", lambda root, params: (_ for _ in ()).throw(RuntimeError))
    with pytest.raises(RuntimeError):
        sources.synthetic_scene_sets("default")
    import mogaf.synth

    code = sources.code_digest(Path(mogaf.synth.__file__).parent)
    assert folders == [("bench_forecast", f"synthetic_default_{code}")]
