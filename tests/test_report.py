"""Reports (mogaf.report.tables, .runtime, .glance) from hand-made metrics.json files.

The files are built with the structure mogaf.evaluate.stage.run_evaluate_stage
writes (and written the same way: evaluate._round, then write_json), so the
tables see exactly what the pipeline gives them.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from typing import Any

import pytest

from mogaf.artefact import write_json
from mogaf.evaluate.stage import _round
from mogaf.forecast.registry import defaults
from mogaf.report import NO_RESULT, load_metrics
from mogaf.report.glance import END, START, glance_table, replace_section, write_section
from mogaf.report.runtime import collect_points, pareto_front, write_runtime_report
from mogaf.report.table_format import MISSING
from mogaf.report.tables import (
    AVERAGE_NOTE,
    METHOD_LABELS,
    TABLE_NAMES,
    build_tables,
    dnerf_table,
    fmt,
    forecast_table,
    groupwise_table,
    iphone_table,
    main_table_paths,
    write_tables,
)

ABLATIONS = {
    "variants": {
        "lw_opt_fc": {"labels": {"encoder": "LW", "opt": True, "forecast": True}},
        "hc_opt_fc": {"labels": {"encoder": "HC", "opt": True, "forecast": True}},
        "gaga4d": {"labels": {"grouping": "Gaga-4D"}},
        "no_masking": {"labels": {"masking": False}},
        "rt_fast": {"labels": {"knob": "iterations x0.25"}},
    },
}


def method_section(
    image: dict[str, float], *, method: str, wall: float, epe: float | None = None, params: dict[str, Any] | None = None
) -> dict[str, Any]:
    """methods.<m> as evaluate.run_evaluate_stage writes it."""
    tracking = None
    if epe is not None:
        tracking = {
            "epe_3d": epe,
            "delta_3d@0.05": 0.4,
            "delta_3d@0.10": 0.6,
            "aj": 0.3,
            "delta_avg": 0.5,
            "occlusion_accuracy": 0.8,
        }
    return {
        "image": dict(image),
        "per_view": [{"frame": "1_00040", "timestep": 40, **image}],
        "tracking": tracking,
        "forecast": {
            "method": method,
            "groupwise": True,
            "num_groups_trained": 2,
            "params": defaults(method) if params is None else params,
            "jobs": {"1": {"final_loss": 0.1}},
        },
        "runtime": {"total_wall_s": wall},
    }


def write_metrics(
    path: Path,
    *,
    dataset: str,
    scene: str,
    ratio: float,
    protocol: str,
    methods: dict[str, Any],
    variant: str = "default",
    grouping: dict[str, Any] | None = None,
) -> Path:
    result = {
        "mogaf_version": "0.0.0",
        "dataset": dataset,
        "scene": scene,
        "ratio": ratio,
        "variant": variant,
        "protocol": protocol,
        "num_evaluation_views": 1,
        "forecast_timesteps": [40, 41],
        "methods": methods,
        "reconstruction": {"heldout_observed": {"psnr": 25.0}, "num_frames": 1},
        "grouping": grouping or {"method": "ours", "num_groups": 3, "ari": 0.9, "mean_iou": 0.8},
        "runtime": {
            "stages": {"recon": {"wall_s": 100.0, "max_rss_mb": 500.0}},
            "total_wall_s": {m: s["runtime"]["total_wall_s"] for m, s in methods.items()},
        },
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_json(path, _round(result))


IPHONE_A = {
    "mogaf": {"mpsnr": 17.123456, "mssim": 0.612345, "mlpips": 0.351234, "psnr": 16.5, "ssim": 0.6, "lpips": 0.4},
    "frozen": {"mpsnr": 15.5, "mssim": 0.55, "mlpips": 0.42, "psnr": 15.0, "ssim": 0.5, "lpips": 0.45},
}
IPHONE_B = {
    "mogaf": {"mpsnr": 18.987654, "mssim": 0.701111, "mlpips": 0.300049, "psnr": 17.5, "ssim": 0.65, "lpips": 0.35}
}
DNERF_C = {
    "mogaf": {"psnr": 22.25, "ssim": 0.912345, "lpips": 0.081234},
    "ode": {"psnr": 21.5, "ssim": 0.9, "lpips": 0.09},
}


@pytest.fixture
def metrics_files(tmp_path) -> list[Path]:
    ode_params = {**defaults("ode"), "epochs": 20}
    return [
        write_metrics(
            tmp_path / "iphone/a/metrics.json",
            dataset="iphone",
            scene="a",
            ratio=0.6,
            protocol="iphone",
            methods={
                m: method_section(v, method=m, wall=100.0 + i, epe=0.1 * (i + 1))
                for i, (m, v) in enumerate(IPHONE_A.items())
            },
        ),
        write_metrics(
            tmp_path / "iphone/b/metrics.json",
            dataset="iphone",
            scene="b",
            ratio=0.6,
            protocol="iphone",
            methods={"mogaf": method_section(IPHONE_B["mogaf"], method="mogaf", wall=210.4)},
        ),
        write_metrics(
            tmp_path / "dnerf/c/metrics.json",
            dataset="dnerf",
            scene="c",
            ratio=0.8,
            protocol="dnerf",
            methods={
                "mogaf": method_section(DNERF_C["mogaf"], method="mogaf", wall=50.0),
                "ode": method_section(DNERF_C["ode"], method="ode", wall=75.6, params=ode_params),
            },
        ),
    ]


def md_rows(md: str) -> list[list[str]]:
    rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in md.splitlines() if line.startswith("|")]
    return [r for r in rows if not all(set(c) <= {"-"} for c in r)]


# ------------------------------------------------------------------ tables
def test_write_tables_writes_every_format(metrics_files, tmp_path):
    outs = main_table_paths(tmp_path / "tables")
    assert len(outs) == 4 * len(TABLE_NAMES)
    written = write_tables([str(p) for p in metrics_files], outs, {}, ABLATIONS)
    assert sorted(map(str, written)) == sorted(outs)
    for name in TABLE_NAMES:
        md = Path(tmp_path / "tables" / f"table_{name}.md").read_text()
        tex = Path(tmp_path / "tables" / f"table_{name}.tex").read_text()
        rows = list(csv.reader(io.StringIO(Path(tmp_path / "tables" / f"table_{name}.csv").read_text())))
        page = Path(tmp_path / "tables" / f"table_{name}.html").read_text()
        # the HTML table has the CSV's rows (one more header row where columns span a heading)
        assert (
            page.startswith("<!DOCTYPE html>")
            and page.count("<tr>") in (len(rows), len(rows) + 1)
            or (len(rows) == 1 and "<table>" not in page and NO_RESULT in page)
        )
        assert md.startswith("### ") and md.endswith("\n")
        assert tex.startswith(r"\begin{table}") and tex.endswith("\\end{table}\n")
        assert rows and all(len(r) == len(rows[0]) for r in rows)
        if len(rows) > 1:  # a table with results
            assert r"\end{tabular}" in tex and tex.count(r"\\") >= 2 and "| " in md
        else:  # no ablation variant was run: one line, no table of "no result"
            assert name in ("grouping", "groupwise", "masking")
            assert NO_RESULT in md and "|" not in md and r"\begin{tabular}" not in tex
    with pytest.raises(ValueError, match="unexpected table output"):
        write_tables([str(p) for p in metrics_files], [str(tmp_path / "table_nosuch.md")], {}, ABLATIONS)


def test_iphone_table_numbers_missing_cells_and_average(metrics_files):
    t = iphone_table(load_metrics(metrics_files))
    # methods in METHOD_ORDER: mogaf before frozen; 3 masked metrics each
    assert t.columns == ["Obs. ratio", "Scene"] + ["mPSNR↑", "mSSIM↑", "mLPIPS↓"] * 2
    assert [label for label, _ in t.spans] == ["", METHOD_LABELS["mogaf"], METHOD_LABELS["frozen"]]
    rows = {r[1]: r for r in t.rows}
    assert set(rows) == {"iphone/a", "iphone/b", "Average"}  # the D-NeRF result is not in the iPhone table
    a, b, avg = rows["iphone/a"], rows["iphone/b"], rows["Average"]
    assert a[0] == "60%"
    assert a[2:] == ["17.12", "0.6123", "0.3512", "15.50", "0.5500", "0.4200"]
    # scene b has no frozen result: dashes among the present cells
    assert b[2:] == ["18.99", "0.7011", "0.3000", MISSING, MISSING, MISSING]
    # averages: means of the rows' values; frozen, without scene b, has none (one scene's would not compare)
    assert avg[2] == f"{(17.123456 + 18.987654) / 2:.2f}"
    assert avg[3] == f"{(0.612345 + 0.701111) / 2:.4f}"
    assert avg[4] == f"{(0.351234 + 0.300049) / 2:.4f}"
    assert avg[5:] == [MISSING, MISSING, MISSING]
    assert AVERAGE_NOTE in t.notes
    md = t.markdown()
    assert "| 60% | iphone/b | 18.99 | 0.7011 | 0.3000 | – | – | – |" in md and NO_RESULT not in md
    # no method here ran off its defaults
    assert "*" not in "".join(label for label, _ in t.spans) and not any(n.startswith("*") for n in t.notes)


def test_dnerf_table_and_off_default_marker(metrics_files):
    t = dnerf_table(load_metrics(metrics_files))
    assert t.columns == ["Obs. ratio", "Scene"] + ["PSNR↑", "SSIM↑", "LPIPS↓"] * 2
    labels = [label for label, _ in t.spans]
    assert labels == ["", METHOD_LABELS["ode"] + "*", METHOD_LABELS["mogaf"]]
    assert t.rows == [["80%", "dnerf/c", "21.50", "0.9000", "0.0900", "22.25", "0.9123", "0.0812"]]
    notes = [n for n in t.notes if n.startswith("*")]
    assert len(notes) == 1 and METHOD_LABELS["ode"] in notes[0]
    assert "epochs (default 40) = 20" in notes[0]
    assert METHOD_LABELS["mogaf"] not in notes[0]
    assert notes[0] in t.markdown()


def test_forecast_table_rows_equal_the_files(metrics_files):
    results = load_metrics(metrics_files)
    t = forecast_table(results)
    assert len(t.rows) == 2 + 1 + 2
    by = {(r[1], r[4]): r for r in t.rows}
    mogaf_a = by[("a", METHOD_LABELS["mogaf"])]
    assert mogaf_a[:4] == ["iphone", "a", "0.6", "default"]
    assert mogaf_a[5:] == [
        fmt(16.5, "psnr"),
        fmt(0.6, "ssim"),
        fmt(0.4, "lpips"),
        fmt(17.123456, "mpsnr"),
        "0.100",
        "100",
    ]
    assert by[("b", METHOD_LABELS["mogaf"])][-2:] == [MISSING, "210"]  # no tracking; 210.4 s to 0 digits
    ode_c = by[("c", METHOD_LABELS["ode"] + "*")]
    assert ode_c[5:] == ["21.50", "0.9000", "0.0900", MISSING, MISSING, "76"]
    # the CSV leaves a missing cell empty
    rows = list(csv.reader(io.StringIO(t.csv())))
    ode_csv = next(r for r in rows if r[1] == "c" and r[4] == METHOD_LABELS["ode"] + "*")
    assert ode_csv[5:] == ["21.50", "0.9000", "0.0900", "", "", "76"]
    assert any("epochs (default 40) = 20" in n for n in t.notes)


def test_gcn_off_defaults_is_marked(tmp_path):
    gcn = {**defaults("gcn"), "epochs": 20, "num_threads": 4}
    f = write_metrics(
        tmp_path / "m.json",
        dataset="d",
        scene="s",
        ratio=0.8,
        protocol="dnerf",
        methods={"gcn": method_section({"psnr": 20.0, "ssim": 0.9, "lpips": 0.1}, method="gcn", wall=10.0, params=gcn)},
    )
    t = dnerf_table(load_metrics([f]))
    assert t.spans[1][0] == METHOD_LABELS["gcn"] + "*"
    note = next(n for n in t.notes if n.startswith("*"))
    assert "epochs (default 2001) = 20" in note
    assert "num_threads" not in note  # a runtime knob, not a budget


def test_gcn_at_defaults_is_not_marked(tmp_path):
    f = write_metrics(
        tmp_path / "m.json",
        dataset="d",
        scene="s",
        ratio=0.8,
        protocol="dnerf",
        methods={"gcn": method_section({"psnr": 20.0, "ssim": 0.9, "lpips": 0.1}, method="gcn", wall=10.0)},
    )
    t = dnerf_table(load_metrics([f]))
    assert t.spans[1][0] == METHOD_LABELS["gcn"]
    assert not any(n.startswith("*") for n in t.notes)


def test_empty_tables_say_so_in_one_line(tmp_path):
    tables = build_tables([], ABLATIONS)
    assert set(tables) == set(TABLE_NAMES)
    for name in TABLE_NAMES:
        t = tables[name]
        assert t.rows == []
        md, tex = t.markdown(), t.latex()
        # one line, not a row of "no result" under every column
        assert md.count(NO_RESULT) == 1 and "|" not in md
        assert tex.count(NO_RESULT) == 1 and r"\begin{tabular}" not in tex
        assert t.csv().splitlines() == [",".join(t.columns)]  # the CSV keeps its header


def test_tables_leave_out_what_was_not_run(tmp_path):
    """Columns, rows and methods with no result in any file are not printed
    (they were printed as "no result" in every cell before)."""
    dnerf = {"psnr": 22.0, "ssim": 0.9, "lpips": 0.1}  # no masked metrics, no tracking
    files = [
        write_metrics(
            tmp_path / f"{s}.json",
            dataset="dnerf",
            scene=s,
            ratio=0.8,
            protocol="dnerf",
            methods={
                "mogaf": method_section(dnerf, method="mogaf", wall=10.0),
                # frozen ran but scored nothing: no image metric, no tracking
                "frozen": method_section({}, method="frozen", wall=1.0),
            },
        )
        for s in ("c", "d")
    ]
    files.append(
        write_metrics(
            tmp_path / "lw.json",
            dataset="dnerf",
            scene="c",
            ratio=0.8,
            protocol="dnerf",
            variant="lw_opt_fc",
            methods={"mogaf": method_section(dnerf, method="mogaf", wall=10.0, epe=0.2)},
        )
    )
    tables = build_tables(load_metrics(files), ABLATIONS)
    text = "".join(t.markdown() + t.latex() + t.csv() for t in tables.values())
    assert NO_RESULT not in text.replace(tables["iphone"].empty_line(), "").replace(
        tables["grouping"].empty_line(), ""
    ).replace(tables["masking"].empty_line(), "")
    f = tables["forecast"]
    assert f.columns == [
        "dataset",
        "scene",
        "ratio",
        "variant",
        "method",
        "PSNR↑",
        "SSIM↑",
        "LPIPS↓",
        "EPE↓",
        "time [s]",
    ]  # no mPSNR
    # frozen's rows keep their run time; the default results have no tracking: a dash among present EPEs
    assert [r[-2:] for r in f.rows if r[4] == METHOD_LABELS["frozen"]] == [[MISSING, "1"], [MISSING, "1"]]
    d = tables["dnerf"]
    # frozen has no image metric in any file: its columns and header go
    assert [label for label, _ in d.spans] == ["", METHOD_LABELS["mogaf"]]
    assert d.columns == ["Obs. ratio", "Scene", "PSNR↑", "SSIM↑", "LPIPS↓"]
    assert [r[1] for r in d.rows] == ["dnerf/c", "dnerf/d", "Average"]
    assert AVERAGE_NOTE not in d.notes  # frozen, pruned, has no value at all: no dash to explain
    # group-wise ablation: only the variant that ran has a row (HC has none)
    g = groupwise_table(load_metrics(files), ABLATIONS)
    assert [r[0] for r in g.rows] == ["LW (1 results)"]
    assert g.rows[0][3:] == ["0.200", "60.0", "40.0", "30.0", "50.0", "80.0"]
    # nothing of the iPhone layout was run: one line, no table
    assert tables["iphone"].rows == [] and "|" not in tables["iphone"].markdown()


def test_grouping_and_masking_ablation_tables(tmp_path):
    img = lambda x: {"mpsnr": x, "mssim": 0.5, "mlpips": 0.3, "psnr": x - 1, "ssim": 0.5, "lpips": 0.3}  # noqa: E731
    default = write_metrics(
        tmp_path / "d.json",
        dataset="iphone",
        scene="a",
        ratio=0.6,
        protocol="iphone",
        methods={"mogaf": method_section(img(18.0), method="mogaf", wall=10.0)},
        grouping={"method": "ours", "num_groups": 3, "ari": 0.9, "mean_iou": 0.8},
    )
    gaga = write_metrics(
        tmp_path / "g.json",
        dataset="iphone",
        scene="a",
        ratio=0.6,
        protocol="iphone",
        variant="gaga4d",
        methods={"mogaf": method_section(img(16.0), method="mogaf", wall=10.0)},
        grouping={"method": "gaga4d", "num_groups": 5, "ari": 0.5, "mean_iou": 0.4},
    )
    nomask = write_metrics(
        tmp_path / "n.json",
        dataset="iphone",
        scene="a",
        ratio=0.6,
        protocol="iphone",
        variant="no_masking",
        methods={
            "mogaf": method_section(
                img(17.0), method="mogaf", wall=10.0, params={**defaults("mogaf"), "masking": False}
            )
        },
    )
    tables = build_tables(load_metrics([default, gaga, nomask]), ABLATIONS)
    g = {r[1]: r for r in tables["grouping"].rows}
    assert set(g) == {"Gaga-4D", "Ours"}
    assert g["Gaga-4D"][0] == "iphone 60% (1 scene)"
    assert g["Gaga-4D"][2] == "16.00" and g["Ours"][2] == "18.00"  # masked PSNR for the iPhone layout
    assert g["Gaga-4D"][-2:] == ["0.500", "0.400"] and g["Ours"][-2:] == ["0.900", "0.800"]
    m = {r[1]: r for r in tables["masking"].rows}
    assert m["Ours w/o masking"][2] == "16.00" and m["Ours"][2] == "17.00"  # the masking table shows plain PSNR
    # variants stay out of the paper-layout table
    assert [r[1] for r in tables["iphone"].rows] == ["iphone/a"]


# ------------------------------------------------------------------ runtime
def test_pareto_front_hand_example():
    pts = [
        {"wall_s": w, "psnr": e, "id": i}
        for i, (w, e) in enumerate([(10, 20.0), (20, 25.0), (30, 22.0), (40, 26.0), (40, 24.0), (5, 19.0)])
    ]
    assert [p["id"] for p in pareto_front(pts, "psnr")] == [5, 0, 1, 3]
    # lower is better for an error such as EPE
    pts = [
        {"wall_s": w, "epe_3d": e, "id": i}
        for i, (w, e) in enumerate([(10, 0.5), (20, 0.3), (30, 0.4), (40, 0.1), (20, 0.2)])
    ]
    assert [p["id"] for p in pareto_front(pts, "epe_3d")] == [0, 4, 3]
    assert pareto_front([], "psnr") == []


def _runtime_files(tmp_path: Path) -> list[Path]:
    files = []
    # (variant, mogaf (wall, psnr), frozen (wall, psnr))
    for variant, mg, fz in [
        ("default", (100.0, 20.0), (60.0, 15.0)),
        ("rt_half", (70.0, 21.0), (40.0, 15.5)),
        ("rt_fast", (50.0, 18.0), (45.0, 14.0)),
        ("unrelated", (10.0, 30.0), (10.0, 30.0)),
    ]:
        files.append(
            write_metrics(
                tmp_path / variant / "metrics.json",
                dataset="iphone",
                scene="a",
                ratio=0.6,
                protocol="iphone",
                variant=variant,
                methods={
                    "mogaf": method_section({"psnr": mg[1]}, method="mogaf", wall=mg[0]),
                    "frozen": method_section({"psnr": fz[1]}, method="frozen", wall=fz[0]),
                },
            )
        )
    return files


def test_runtime_points_and_report(tmp_path):
    files = _runtime_files(tmp_path)
    params = {"error_metric": "psnr", "runtime_variants": ["rt_half", "rt_fast"]}
    points = collect_points(load_metrics(files), "psnr", params["runtime_variants"])
    assert len(points) == 6 and "unrelated" not in {p["variant"] for p in points}
    out = tmp_path / "report"
    written = write_runtime_report(
        [str(f) for f in files], str(out / "e.csv"), str(out / "e.md"), str(out / "e.png"), params
    )
    assert [p.name for p in written] == ["e.csv", "e.md", "e.png"]
    assert (out / "e.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = list(csv.DictReader(io.StringIO((out / "e.csv").read_text())))
    on = {(r["method"], r["variant"]): r["on Pareto line"] for r in rows}
    # mogaf: default (100 s, 20) is beaten by rt_half (70 s, 21); rt_fast (50 s, 18) is the fastest
    assert on[(METHOD_LABELS["mogaf"], "rt_half")] == "yes"
    assert on[(METHOD_LABELS["mogaf"], "rt_fast")] == "yes"
    assert on[(METHOD_LABELS["mogaf"], "default")] == "no"
    # frozen: rt_half (40 s, 15.5) beats both others
    assert on[(METHOD_LABELS["frozen"], "rt_half")] == "yes"
    assert on[(METHOD_LABELS["frozen"], "default")] == "no" and on[(METHOD_LABELS["frozen"], "rt_fast")] == "no"
    row = next(r for r in rows if r["variant"] == "rt_half" and r["method"] == METHOD_LABELS["mogaf"])
    assert row["wall time [s]"] == "70.0" and row["PSNR↑"] == "21.00" and row["ratio"] == "0.6"
    md_body = md_rows((out / "e.md").read_text())
    assert len(md_body) == 1 + 6


def test_runtime_report_without_points(tmp_path):
    out = tmp_path / "r"
    write_runtime_report([], str(out / "e.csv"), str(out / "e.md"), str(out / "e.png"), {"error_metric": "epe_3d"})
    assert (out / "e.csv").read_text().splitlines()[0].startswith("dataset,scene")
    assert NO_RESULT in (out / "e.md").read_text()
    assert (out / "e.png").stat().st_size > 0


def test_load_metrics_rejects_foreign_json(tmp_path):
    from mogaf.errors import MogafError

    bad = tmp_path / "bad.json"
    bad.write_text('{"dataset": "x"}')
    with pytest.raises(MogafError, match="no 'methods' section"):
        load_metrics([bad])
    bad.write_text("{not json")
    with pytest.raises(MogafError, match="not readable JSON"):
        load_metrics([bad])
    with pytest.raises(MogafError, match=r"absent\.json: no such metrics file"):  # a mistyped path is not "no result"
        load_metrics([tmp_path / "absent.json"])


# ------------------------------------------------------------------ glance (README "Results at a glance")
# The demo's numbers, as the README gives them (make demo, results/synthetic/default/ratio0.6/metrics.json,
# rounded as printed): method -> (PSNR, LPIPS, mPSNR, tracking EPE); GCN and ODE at config/demo.yaml's budgets.
DEMO = {
    "gcn": (15.80, 0.2771, 20.36, 0.466),
    "ode": (15.85, 0.3252, 19.89, 1.599),
    "mogaf": (16.58, 0.1933, 23.19, 0.097),
    "mogaf_paper": (16.10, 0.2373, 21.27, 0.199),
    "constant_velocity": (16.27, 0.2191, 21.88, 0.164),
    "frozen": (16.42, 0.2127, 22.43, 0.156),
}
DEMO_FILE = "results/synthetic/default/ratio0.6/metrics.json"


def _demo_metrics(root: Path) -> Path:
    params = {
        "gcn": {**defaults("gcn"), "epochs": 20},
        "ode": {**defaults("ode"), "epochs": 1, "max_gaussians_per_epoch": 256},
    }
    methods = {
        m: method_section(
            {"psnr": p, "lpips": lp, "mpsnr": mp, "ssim": 0.5}, method=m, wall=10.0, epe=epe, params=params.get(m)
        )
        for m, (p, lp, mp, epe) in DEMO.items()
    }
    return write_metrics(
        root / DEMO_FILE, dataset="synthetic", scene="default", ratio=0.6, protocol="iphone", methods=methods
    )


def test_glance_table_marks_the_best_and_the_shortened_budgets(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _demo_metrics(tmp_path)
    lines = glance_table(load_metrics([DEMO_FILE])).splitlines()
    assert lines[0] == f"From `{DEMO_FILE}`; best in bold."
    assert lines[2] == "| method | PSNR↑ | LPIPS↓ | mPSNR↑ | tracking EPE (m)↓ |"
    rows = md_rows("\n".join(lines))[1:]
    assert [r[0] for r in rows] == [
        METHOD_LABELS["gcn"] + "*",
        METHOD_LABELS["ode"] + "*",
        METHOD_LABELS["mogaf"],
        METHOD_LABELS["mogaf_paper"],
        METHOD_LABELS["constant_velocity"],
        METHOD_LABELS["frozen"],
    ]
    assert rows[2][1:] == ["**16.58**", "**0.1933**", "**23.19**", "**0.097**"]  # higher PSNR, lower LPIPS / EPE
    assert rows[5][1:] == ["16.42", "0.2127", "22.43", "0.156"]
    assert lines[-1].startswith("Methods marked * ran off their papers' settings")


def test_glance_table_leaves_out_what_was_not_run(metrics_files):
    # the D-NeRF file has no masked metric and no tracking: two columns, no dash-only column
    lines = glance_table(load_metrics([metrics_files[2]])).splitlines()
    assert lines[2] == "| method | PSNR↑ | LPIPS↓ |"
    assert md_rows("\n".join(lines))[1:] == [
        [METHOD_LABELS["ode"] + "*", "21.50", "0.0900"],
        [METHOD_LABELS["mogaf"], "**22.25**", "**0.0812**"],
    ]
    # several files: a row per result and method, the best marked per result
    rows = md_rows(glance_table(load_metrics(metrics_files)))
    assert rows[0] == ["result", "method", "PSNR↑", "LPIPS↓", "mPSNR↑", "tracking EPE (m)↓"]
    assert [r[:2] for r in rows[1:]] == [
        ["dnerf/c 0.8", METHOD_LABELS["ode"] + "*"],
        ["dnerf/c 0.8", METHOD_LABELS["mogaf"]],
        ["iphone/a 0.6", METHOD_LABELS["mogaf"]],
        ["iphone/a 0.6", METHOD_LABELS["frozen"]],
        ["iphone/b 0.6", METHOD_LABELS["mogaf"]],
    ]
    assert rows[5][2:] == ["**17.50**", "**0.3500**", "**18.99**", MISSING]


def test_glance_section_is_replaced_between_the_markers(tmp_path):
    from mogaf.errors import MogafError

    doc = tmp_path / "README.md"
    doc.write_text(f"# x\n\nbefore\n{START}\nold table\n{END}\nafter\n")
    assert write_section(doc, "| new |\n") is True
    assert doc.read_text() == f"# x\n\nbefore\n{START}\n| new |\n{END}\nafter\n"
    assert write_section(doc, "| new |") is False  # already there: the file is left alone
    doc.write_text("# no markers\n")
    with pytest.raises(MogafError, match=r"README\.md: has no '<!-- glance:start -->'"):
        write_section(doc, "| new |\n")
    assert doc.read_text() == "# no markers\n"


def test_glance_cli_writes_and_checks(tmp_path, monkeypatch, capsys):
    from mogaf.report.__main__ import main

    monkeypatch.chdir(tmp_path)
    _demo_metrics(tmp_path)
    doc = tmp_path / "doc.md"
    doc.write_text(f"{START}\n{END}\n")
    assert main(["glance", DEMO_FILE, "--check", str(doc)]) == 1
    assert "glance section differs" in capsys.readouterr().err
    assert main(["glance", DEMO_FILE, "--write", str(doc)]) == 0
    assert main(["glance", DEMO_FILE, "--check", str(doc)]) == 0
    assert main(["glance", DEMO_FILE]) == 0
    assert capsys.readouterr().out.endswith(glance_table(load_metrics([DEMO_FILE])))
    assert main(["glance", "absent.json"]) == 1
    assert capsys.readouterr().err.strip() == "mogaf.report: error: absent.json: no such metrics file"


def test_readme_glance_section_is_what_the_generator_prints(tmp_path, monkeypatch):
    """The README's table is the generator's output for the demo's numbers."""
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    assert readme.count(START) == 1 and readme.count(END) == 1
    assert f"python -m mogaf.report glance {DEMO_FILE} --write README.md" in readme
    monkeypatch.chdir(tmp_path)
    _demo_metrics(tmp_path)
    block = glance_table(load_metrics([DEMO_FILE]))
    assert replace_section(readme, block) == readme


def test_scenes_table_compares_the_methods_every_scene_ran(metrics_files):
    from mogaf.report.scenes import scenes_table

    text = scenes_table(load_metrics(metrics_files))
    first, second = text.split("Ratio ")[1:]
    # ratio 0.6: frozen ran on scene a only, so only MoGaF is compared; the mean is over a and b
    assert first.startswith("0.6 (iphone; PSNR / LPIPS)")
    rows = md_rows(first)
    assert rows[0][:2] == ["scene", METHOD_LABELS["mogaf"]] and len(rows[0]) == 5
    assert [r[:2] for r in rows[1:]] == [
        ["a", "**16.50** / **0.4000**"],
        ["b", "**17.50** / **0.3500**"],
        ["**mean**", "**17.00** / **0.3750**"],
    ]
    # ratio 0.8: the shortened ODE is starred and loses to MoGaF on both figures
    rows = md_rows(second)
    assert rows[0][1:3] == [METHOD_LABELS["ode"] + "*", METHOD_LABELS["mogaf"]]
    assert rows[1][1:3] == ["21.50 / 0.0900", "**22.25** / **0.0812**"]
    assert "ran off its paper's settings" in second


def test_scenes_table_adds_tracking_epe_only_where_every_scene_has_it(tmp_path):
    from mogaf.report.scenes import scenes_table

    def scene(name: str, ratio: float, frozen_epe: float | None) -> Path:
        return write_metrics(
            tmp_path / f"synthetic/{name}/{ratio}/metrics.json",
            dataset="synthetic",
            scene=name,
            ratio=ratio,
            protocol="dnerf",
            methods={
                "mogaf": method_section({"psnr": 17.0, "lpips": 0.20}, method="mogaf", wall=10.0, epe=0.10),
                "frozen": method_section({"psnr": 16.0, "lpips": 0.25}, method="frozen", wall=1.0, epe=frozen_epe),
            },
        )

    # ratio 0.6: both scenes track every method; frozen wins scene b's EPE, MoGaF the mean
    # ratio 0.8: frozen has no tracking on scene d, so that ratio's cells stay PSNR / LPIPS
    files = [scene("a", 0.6, 0.30), scene("b", 0.6, 0.05), scene("c", 0.8, 0.30), scene("d", 0.8, None)]
    first, second = scenes_table(load_metrics(files)).split("Ratio ")[1:]
    assert first.startswith("0.6 (synthetic; PSNR / LPIPS / tracking EPE (m))")
    rows = md_rows(first)
    assert [r[1:3] for r in rows[1:]] == [
        ["**17.00** / **0.2000** / **0.100**", "16.00 / 0.2500 / 0.300"],
        ["**17.00** / **0.2000** / 0.100", "16.00 / 0.2500 / **0.050**"],
        ["**17.00** / **0.2000** / **0.100**", "16.00 / 0.2500 / 0.175"],
    ]
    assert second.startswith("0.8 (synthetic; PSNR / LPIPS)")
    assert md_rows(second)[1][1:3] == ["**17.00** / **0.2000**", "16.00 / 0.2500"]


def test_tables_say_how_many_optimiser_steps_each_group_trained(tmp_path):
    from mogaf.report.scenes import scenes_table
    from mogaf.report.tables import forecast_table, optimiser_steps

    def with_steps(method: str, steps: list[int]) -> dict[str, Any]:
        section = method_section({"psnr": 20.0, "lpips": 0.2}, method=method, wall=10.0)
        section["forecast"]["jobs"] = {str(k): {"iterations": n} for k, n in enumerate(steps)}
        return section

    files = [
        write_metrics(
            tmp_path / f"mujoco/{scene}/metrics.json",
            dataset="mujoco",
            scene=scene,
            ratio=0.8,
            protocol="dnerf",
            methods={
                "gcn": with_steps("gcn", gcn),
                "mogaf_paper": with_steps("mogaf_paper", [800]),
                "constant_velocity": method_section({"psnr": 19.0, "lpips": 0.3}, method="constant_velocity", wall=1.0),
            },
        )
        for scene, gcn in (("s1", [800, 806]), ("s2", [802]))
    ]
    results = load_metrics(files)
    # over every group of every scene; a method that trains nothing records no steps
    assert optimiser_steps(results, "gcn") == (800, 806)
    assert optimiser_steps(results, "constant_velocity") is None
    # in the tables' column order
    note = f"Optimiser steps per motion group (recorded): {METHOD_LABELS['gcn']} 800-806; {METHOD_LABELS['mogaf_paper']} 800"
    assert note + "." in scenes_table(results)
    assert note in forecast_table(results).notes


def test_html_table_escapes_and_keeps_every_cell():
    from mogaf.report.table_format import Table

    t = Table(title="A <b> & c", columns=["scene", "PSNR ↑"], rows=[["x<y", "20.1"], ["z", "–"]], keys=1)
    page = t.html()
    assert "A &lt;b&gt; &amp; c" in page and "<th>x&lt;y</th><td>20.1</td>" in page and "<td>–</td>" in page
    assert page.count("<tr>") == 3


def test_scene_videos_page_plays_every_video_under_its_label(tmp_path, metrics_files):
    """videos_page copies the videos beside an index.html that plays each under
    its method's label (all methods first); a folder without video is one line."""
    import imageio.v3 as iio
    import numpy as np

    from mogaf.errors import MogafError
    from mogaf.report.pages import videos_page

    renders = tmp_path / "renders"
    renders.mkdir()
    for name in ("mogaf", "frozen", "all_methods"):
        (renders / f"{name}.mp4").write_bytes(b"mp4 " + name.encode())
    iio.imwrite(renders / "view.png", np.zeros((2, 2), np.uint8))  # a render PNG: not a video
    out = videos_page(renders, metrics_files[0], tmp_path / "report" / "videos")
    page = (out / "index.html").read_text()
    assert sorted(p.name for p in out.iterdir()) == ["all_methods.mp4", "frozen.mp4", "index.html", "mogaf.mp4"]
    assert page.index('src="all_methods.mp4"') < page.index('src="mogaf.mp4"') < page.index('src="frozen.mp4"')
    assert "<figcaption>MoGaF (Ours)</figcaption>" in page and "<figcaption>Frozen</figcaption>" in page
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(MogafError, match="holds no video"):
        videos_page(empty, metrics_files[0], tmp_path / "report2")


def test_scenes_table_gives_mogafs_margin_over_the_better_of_frozen_and_constant_velocity(tmp_path):
    from mogaf.report.scenes import scenes_table

    def scene(name: str, mogaf: float, frozen: float, cv: float) -> Path:
        return write_metrics(
            tmp_path / f"synthetic/{name}/metrics.json",
            dataset="synthetic",
            scene=name,
            ratio=0.6,
            protocol="dnerf",
            methods={
                "mogaf": method_section({"psnr": mogaf, "lpips": 0.2}, method="mogaf", wall=10.0),
                "frozen": method_section({"psnr": frozen, "lpips": 0.2}, method="frozen", wall=1.0),
                "constant_velocity": method_section({"psnr": cv, "lpips": 0.2}, method="constant_velocity", wall=1.0),
            },
        )

    # a: ahead of both; b: 0.2 dB behind frozen (within the bound); c: 0.5 dB behind constant velocity
    files = [scene("a", 18.0, 17.5, 17.0), scene("b", 17.0, 17.2, 16.0), scene("c", 16.0, 15.0, 16.5)]
    # the grouping's IoU per ground-truth object, where the scene has it
    data = json.loads(files[0].read_text())
    data["grouping"] = {"object_names": ["box", "flag"], "per_object_iou": [0.912, 0.4]}
    files[0].write_text(json.dumps(data))
    data = json.loads(files[1].read_text())  # and per part of an object made of pieces
    data["grouping"] = {
        "object_names": ["chest"],
        "per_object_iou": [0.85],
        "part_names": ["chest/body", "chest/lid"],
        "per_part_iou": [0.8, 0.123],
    }
    files[1].write_text(json.dumps(data))
    for f, psnr in zip(files, (None, 21.0, 23.0), strict=True):  # the reconstruction's held-out PSNR
        data = json.loads(f.read_text())
        data["reconstruction"] = {"heldout_observed": {"psnr": psnr}} if psnr else {}
        if psnr:  # and its velocity error at the last observed step against the GT points' speed
            data["reconstruction"]["observed_motion"] = {"last_velocity_error": psnr / 1000, "speed": 0.01}
        if psnr == 23.0:  # and points that never move: how far MoGaF moves them, against the jitter on them
            data["reconstruction"]["observed_motion"]["still_jitter"] = 0.02
            data["methods"]["mogaf"]["forecast"]["still_points_displacement"] = 0.005
        f.write_text(json.dumps(data))
    text = scenes_table(load_metrics(files))
    rows = md_rows(text)
    col = rows[0].index("MoGaF − best of frozen, const. velocity (dB)")
    assert [r[col] for r in rows[1:4]] == ["+0.50", "-0.20", "-0.50"]
    iou = rows[0].index("grouping IoU per object")
    assert [r[iou] for r in rows[1:4]] == ["box 0.91, flag 0.40", "chest 0.85, chest/body 0.80, chest/lid 0.12", "–"]
    recon = rows[0].index("reconstruction PSNR, held-out views of observed times")
    assert [r[recon] for r in rows[1:5]] == ["–", "21.00", "23.00", "22.00"]  # the mean over the scenes that have it
    velocity = rows[0].index("reconstruction: GT points' velocity error at the last observed step / their speed")
    assert [r[velocity] for r in rows[1:5]] == ["–", "0.0210 / 0.0100", "0.0230 / 0.0100", "0.0220 / 0.0100"]
    still = rows[0].index("GT points that never move: MoGaF moves them / the reconstruction's jitter (m)")
    assert [r[still] for r in rows[1:5]] == ["–", "–", "0.0050 / 0.0200", "0.0050 / 0.0200"]
    assert len({len(r) for r in rows}) == 1  # the mean row has every column
    assert (
        "MoGaF is more than 0.3 dB PSNR below the better of frozen and constant velocity on 1 of 3 scenes "
        "(worst margin -0.50 dB, c)." in text
    )


def test_scene_table_names_each_rigid_parts_decision():
    """A group forecast in rigid parts shows each part's own choice, counted."""
    from mogaf.report.scenes import _choice_text

    info = {"choice": "rigid_parts", "part_choices": "frozen linear_trend linear_trend"}
    assert _choice_text(info) == "rigid parts (frozen, linear trend x2)"
    assert _choice_text({"choice": "linear_trend", "backtest_weight_linear_trend": 0.75}) == "linear trend 0.75"


def test_a_scene_rows_file_keeps_the_tables_of_its_metrics_files(tmp_path, metrics_files, capsys):
    """`scenes --json FILE --run TEXT`: the same tables from the file as from the
    metrics.json files, a record per line without the per-view metrics, and the
    results page prints them under the run's description."""
    from mogaf.report.__main__ import main
    from mogaf.report.results_page import read_bench_dir, results_page
    from mogaf.report.scenes import read_scene_rows, scenes_table

    bench = tmp_path / "bench"
    bench.mkdir()
    kept = bench / "scenes_test.json"
    assert main(["scenes", *map(str, metrics_files), "--json", str(kept), "--run", "a test machine"]) == 0
    printed = capsys.readouterr().out
    assert printed == scenes_table(load_metrics(metrics_files))
    run, records = read_scene_rows(kept)
    assert run == "a test machine" and len(records) == len(metrics_files)
    assert scenes_table(records) == printed
    text = kept.read_text()
    assert "per_view" not in text and len(text.splitlines()) == len(metrics_files) + 3
    assert [(r["scene"], r["ratio"]) for r in records] == [("a", 0.6), ("b", 0.6), ("c", 0.8)]  # table order

    assert read_bench_dir(bench) == ([], [], [(kept, run, records)])
    page = results_page(tmp_path / "out.md", bench)
    assert f"| `{kept.as_posix()}` | `python -m mogaf.report scenes --json` | – | – | – | – | 3 | – |" in page
    section = page.split(f"## Forecasts per scene: `{kept.as_posix()}`\n\nThe run: a test machine. ")[1]
    assert scenes_table(records).rstrip("\n") in section


def test_scenes_check_says_whether_a_rerun_reproduces_a_scene_rows_file(tmp_path, metrics_files, capsys):
    """`scenes --check FILE`: exit 0 when every given result's measured values
    equal its record (wall times may differ), 1 naming the first differing
    value, or a result the file does not hold; no table is printed."""
    from mogaf.report.__main__ import main

    kept = tmp_path / "scenes_test.json"
    assert main(["scenes", *map(str, metrics_files), "--json", str(kept), "--run", "here"]) == 0
    capsys.readouterr()
    rerun = json.loads(metrics_files[0].read_text())
    rerun["runtime"] = {"total_wall_s": {"mogaf": 1.0}}  # a rerun's own wall times
    rerun["methods"]["mogaf"]["runtime"] = {"total_wall_s": 1.0}
    metrics_files[0].write_text(json.dumps(rerun))
    assert main(["scenes", *map(str, metrics_files), "--check", str(kept)]) == 0
    out = capsys.readouterr().out
    assert out == f"{kept}: 3 of 3 results identical (0 of its 3 not given)\n"

    psnr = rerun["methods"]["mogaf"]["image"]["psnr"]
    rerun["methods"]["mogaf"]["image"]["psnr"] = psnr + 1e-6
    metrics_files[0].write_text(json.dumps(rerun))
    assert main(["scenes", str(metrics_files[0]), "--check", str(kept)]) == 1
    lines = capsys.readouterr().out.splitlines()
    assert lines == [
        f"iphone/a 0.6 default: 1 values differ: mogaf.image.psnr: {psnr!r} -> {psnr + 1e-6!r}",
        f"{kept}: 0 of 1 results identical (2 of its 3 not given)",
    ]
    other = write_metrics(
        tmp_path / "iphone/d/metrics.json",
        dataset="iphone",
        scene="d",
        ratio=0.6,
        protocol="iphone",
        methods={"mogaf": method_section(IPHONE_B["mogaf"], method="mogaf", wall=1.0)},
    )
    assert main(["scenes", str(other), "--check", str(kept)]) == 1
    assert capsys.readouterr().out.splitlines()[0] == f"iphone/d 0.6 default: not in {kept}"
    assert main(["scenes", str(other), "--check", str(kept), "--json", str(tmp_path / "b.json"), "--run", "x"]) == 1
    assert "not both" in capsys.readouterr().err and not (tmp_path / "b.json").exists()


def test_a_bad_scene_rows_file_is_one_line_naming_it(tmp_path, metrics_files, capsys):
    from mogaf.errors import MogafError
    from mogaf.report.__main__ import main
    from mogaf.report.scenes import read_scene_rows

    kept = tmp_path / "scenes.json"
    for half in (["--json", str(kept)], ["--run", "here"], ["--json", str(kept), "--run", " "]):
        assert main(["scenes", *map(str, metrics_files), *half]) == 1
        out = capsys.readouterr()
        assert out.out == "" and "go together" in out.err and not kept.exists()  # nothing printed, nothing written
    assert main(["scenes", *map(str, metrics_files), "--json", str(kept), "--run", "here\n## a heading"]) == 1
    out = capsys.readouterr()
    assert out.out == "" and "--run must be one line" in out.err and not kept.exists()
    assert main(["scenes", *map(str, metrics_files), "--json", str(tmp_path / "scenes.md"), "--run", "here"]) == 1
    assert "must end in .json" in capsys.readouterr().err
    assert main(["scenes", *map(str, metrics_files), "--json", str(kept), "--run", "here"]) == 0
    doc = json.loads(kept.read_text())

    def broken(change) -> str:
        bad = json.loads(json.dumps(doc))
        change(bad)
        kept.write_text(json.dumps(bad))
        with pytest.raises(MogafError) as err:
            read_scene_rows(kept)
        assert str(kept) in str(err.value)
        return str(err.value)

    assert "scenes[1]: 'ratio' must be a number in (0, 1)" in broken(lambda d: d["scenes"][1].update(ratio=2.0))
    assert "scenes[0]: 'methods' must be an object" in broken(lambda d: d["scenes"][0].update(methods=[1]))
    assert "'reconstruction.heldout_observed.psnr' must be a number or null" in broken(
        lambda d: d["scenes"][0]["reconstruction"]["heldout_observed"].update(psnr="x")
    )
    assert "'methods.mogaf.forecast.coherence' must be an object" in broken(
        lambda d: d["scenes"][0]["methods"]["mogaf"]["forecast"].update(coherence="x")
    )
    assert "scenes[3] holds the same result as scenes[0]" in broken(lambda d: d["scenes"].append(d["scenes"][0]))
    assert "'run' must say where" in broken(lambda d: d.pop("run"))
    assert "'run' must be one line" in broken(lambda d: d.update(run="a\n## b"))
    assert "non-empty list" in broken(lambda d: d.update(scenes=[]))
    kept.write_text("[1, 2]")
    with pytest.raises(MogafError, match="is not a scene-rows file"):
        read_scene_rows(kept)
    kept.write_text(json.dumps(doc).replace('"psnr": 25.0', '"psnr": 1e400', 1))
    with pytest.raises(MogafError, match="1e400 is beyond the range of a float"):
        read_scene_rows(kept)


def test_a_scene_rows_file_orders_variants_as_the_live_table(tmp_path):
    """A scene with a variant (ablation/<v>/metrics.json, which sorts before the
    default's path): the default's row first, from the files and from the rows."""
    from mogaf.report.scenes import read_scene_rows, scenes_table, write_scene_rows

    def result(path: str, variant: str, psnr: float) -> Path:
        methods = {m: method_section({"psnr": psnr, "lpips": 0.2}, method=m, wall=1.0) for m in ("mogaf", "frozen")}
        return write_metrics(
            tmp_path / path,
            dataset="synthetic",
            scene="a",
            ratio=0.6,
            protocol="dnerf",
            methods=methods,
            variant=variant,
        )

    files = [
        result("a/ratio0.6/metrics.json", "default", 17.0),
        result("a/ratio0.6/ablation/v/metrics.json", "v", 16.0),
    ]
    live = scenes_table(load_metrics(files))
    assert [r[0] for r in md_rows(live)[1:3]] == ["a", "a (v)"]
    write_scene_rows(tmp_path / "rows.json", load_metrics(files), "here")
    assert scenes_table(read_scene_rows(tmp_path / "rows.json")[1]) == live


def test_the_reconstruction_panel_draws_one_line_per_held_out_camera():
    """Frames of two held-out cameras at alternating time steps, one much
    better covered than the other: one PSNR line per camera, each in time
    order over that camera's own frames, not one zigzag through both."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from mogaf.report.pages import reconstruction_panel

    steps = np.array([6, 0, 3, 9, 12, 15])
    cameras = np.array([1, 1, 2, 2, 1, 2])
    psnr = np.array([20.1, 20.0, 16.4, 16.5, 20.2, 16.3])
    recon = {"timesteps": steps, "camera_ids": cameras, "per_frame": {"psnr": psnr, "ssim": psnr / 25.0}}
    fig, ax = plt.subplots()
    try:
        lines = reconstruction_panel(ax, recon)
        assert [line.get_label() for line in lines] == ["camera 1", "camera 2"]
        assert lines[0].get_xdata().tolist() == [0, 6, 12] and lines[0].get_ydata().tolist() == [20.0, 20.1, 20.2]
        assert lines[1].get_xdata().tolist() == [3, 9, 15] and lines[1].get_ydata().tolist() == [16.4, 16.5, 16.3]
        assert "18.25 dB" in ax.get_title()  # the mean over every frame
        ssim = [line for other in fig.axes if other is not ax for line in other.get_lines()]
        assert [line.get_ydata().tolist() for line in ssim] == [
            (psnr[[1, 0, 4]] / 25.0).tolist(),
            (psnr[[2, 3, 5]] / 25.0).tolist(),
        ]
        # without camera ids, or with a camera per frame (D-NeRF's test views): one line over time
        for cameras in (None, np.arange(6)):
            fig.clear()
            (line,) = reconstruction_panel(fig.add_subplot(), {**recon, "camera_ids": cameras})
            assert line.get_xdata().tolist() == sorted(steps.tolist())
            assert line.get_ydata().tolist() == [20.0, 16.4, 20.1, 16.5, 20.2, 16.3]
        # any integer is a camera id, -1 too
        fig.clear()
        lines = reconstruction_panel(fig.add_subplot(), {**recon, "camera_ids": recon["camera_ids"] - 2})
        assert [line.get_label() for line in lines] == ["camera -1", "camera 0"]
    finally:
        plt.close(fig)
