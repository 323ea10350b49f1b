"""The README's timing line: generated from a pipeline benchmark file, never written by hand."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mogaf.errors import MogafError
from mogaf.report.__main__ import main
from mogaf.report.timing import MARKERS, timing_line

ROOT = Path(__file__).resolve().parents[1]


def _rows(path: Path, snakemake_s: float | None = 312.4) -> Path:
    budgets = [
        {"row": "recon", "jobs": 1, "wall_s": 101.2, "cpu_s": 99.0, "budget_s": 60.0, "worst": "", "within": False},
        {"row": "evaluate", "jobs": 1, "wall_s": 19.6, "cpu_s": 19.0, "budget_s": 20.0, "worst": "", "within": True},
    ]
    if snakemake_s is not None:
        budgets.append({"row": "Snakemake run (whole demo)", "jobs": 2, "wall_s": snakemake_s, "cpu_s": None,
                        "budget_s": 180.0, "worst": "", "within": False})  # fmt: skip
    path.write_text(json.dumps({"results": "an idle 2-core test machine", "snakemake_s": snakemake_s,
                                "budgets": budgets, "jobs": []}))  # fmt: skip
    return path


def test_timing_line_states_the_run_and_every_budget_row(tmp_path):
    line = timing_line(_rows(tmp_path / "p.json"))
    assert line.startswith("Measured: the demo's Snakemake run took 5 min 12 s (an idle 2-core test machine)")
    assert "recon 101 s (60), evaluate 20 s (20)." in line
    assert "Snakemake run (whole demo)" not in line


def test_timing_line_refuses_a_file_without_the_whole_run_time(tmp_path):
    with pytest.raises(MogafError, match=r"p\.json: has no whole-run wall time"):
        timing_line(_rows(tmp_path / "p.json", snakemake_s=None))
    (tmp_path / "q.json").write_text('{"rows": []}')
    with pytest.raises(MogafError, match=r"q\.json: not `python -m mogaf.bench pipeline --json` output"):
        timing_line(tmp_path / "q.json")


def test_timing_cli_writes_and_checks_only_its_section(tmp_path, capsys):
    rows = _rows(tmp_path / "p.json")
    doc = tmp_path / "README.md"
    doc.write_text(f"# x\n<!-- glance:start -->\nkept\n<!-- glance:end -->\n{MARKERS[0]}\nold\n{MARKERS[1]}\n")
    assert main(["timing", str(rows), "--check", str(doc)]) == 1
    assert "timing section differs" in capsys.readouterr().err
    assert main(["timing", str(rows), "--write", str(doc)]) == 0
    assert main(["timing", str(rows), "--check", str(doc)]) == 0
    assert "kept" in doc.read_text() and "old" not in doc.read_text()


def test_readme_timing_line_is_the_committed_benchmark(monkeypatch):
    monkeypatch.chdir(ROOT)
    assert main(["timing", "results/bench/pipeline_demo_cpu.json", "--check", "README.md"]) == 0


@pytest.mark.parametrize(
    "change, words",
    [
        ({"snakemake_s": -65}, "'snakemake_s' is -65; expected a finite number of seconds >= 0"),
        ({"budgets": [{"row": "x", "wall_s": "abc", "budget_s": 5}]}, "budgets[0] is {'row': 'x', 'wall_s': 'abc'"),
        ({"budgets": [3]}, "budgets[0] is 3; expected an object"),
    ],
)
def test_timing_line_refuses_rows_that_are_not_seconds(tmp_path, change, words):
    path = _rows(tmp_path / "p.json")
    path.write_text(json.dumps({**json.loads(path.read_text()), **change}))
    with pytest.raises(MogafError) as exc:
        timing_line(path)
    assert str(exc.value).startswith(f"{path}: {words}")


def test_a_page_that_is_not_utf8_text_is_one_line(tmp_path, capsys):
    doc = tmp_path / "README.md"
    doc.write_bytes(b"\xff\xfe" + "\n".join(MARKERS).encode())
    for flag in ("--write", "--check"):
        assert main(["timing", str(_rows(tmp_path / "p.json")), flag, str(doc)]) == 1
        assert f"{doc}: is not UTF-8 text (byte 0)" in capsys.readouterr().err
