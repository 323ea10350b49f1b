"""Reports (mogaf.report.tables, mogaf.report.runtime) from hand-made metrics.json files.

The files are built with the structure mogaf.evaluate.run_evaluate_stage
writes (and written the same way: evaluate._round, then write_json), so the
tables see exactly what the pipeline gives them.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any

import pytest

from mogaf.artefact import write_json
from mogaf.evaluate import _round
from mogaf.forecast import defaults
from mogaf.report import NO_RESULT, load_metrics
from mogaf.report.runtime import collect_points, pareto_front, write_runtime_report
from mogaf.report.tables import (
    METHOD_LABELS,
    TABLE_NAMES,
    build_tables,
    dnerf_table,
    fmt,
    forecast_table,
    iphone_table,
    main_table_paths,
    write_tables,
)

ABLATIONS = {
    "variants": {
        "gaga4d": {"labels": {"grouping": "Gaga-4D"}},
        "no_masking": {"labels": {"masking": False}},
        "rt_fast": {"labels": {"knob": "iterations x0.25"}},
    },
}


def method_section(image: dict[str, float], *, method: str, wall: float, epe: float | None = None,
                   params: dict[str, Any] | None = None) -> dict[str, Any]:
    """methods.<m> as evaluate.run_evaluate_stage writes it."""
    tracking = None
    if epe is not None:
        tracking = {"epe_3d": epe, "delta_3d@0.05": 0.4, "delta_3d@0.10": 0.6, "aj": 0.3, "delta_avg": 0.5,
                    "occlusion_accuracy": 0.8}
    return {
        "image": dict(image),
        "per_view": [{"frame": "1_00040", "timestep": 40, **image}],
        "tracking": tracking,
        "forecast": {"method": method, "groupwise": True, "num_groups_trained": 2,
                     "params": defaults(method) if params is None else params, "jobs": {"1": {"final_loss": 0.1}}},
        "runtime": {"total_wall_s": wall},
    }


def write_metrics(path: Path, *, dataset: str, scene: str, ratio: float, protocol: str, methods: dict[str, Any],
                  variant: str = "default", grouping: dict[str, Any] | None = None) -> Path:
    result = {
        "mogaf_version": "0.0.0",
        "dataset": dataset, "scene": scene, "ratio": ratio, "variant": variant, "protocol": protocol,
        "num_evaluation_views": 1, "forecast_timesteps": [40, 41],
        "methods": methods,
        "reconstruction": {"heldout_observed": {"psnr": 25.0}, "num_frames": 1},
        "grouping": grouping or {"method": "ours", "num_groups": 3, "ari": 0.9, "mean_iou": 0.8},
        "runtime": {"stages": {"recon": {"wall_s": 100.0, "max_rss_mb": 500.0}},
                    "total_wall_s": {m: s["runtime"]["total_wall_s"] for m, s in methods.items()}},
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_json(path, _round(result))


IPHONE_A = {"mogaf": {"mpsnr": 17.123456, "mssim": 0.612345, "mlpips": 0.351234, "psnr": 16.5, "ssim": 0.6, "lpips": 0.4},
            "frozen": {"mpsnr": 15.5, "mssim": 0.55, "mlpips": 0.42, "psnr": 15.0, "ssim": 0.5, "lpips": 0.45}}
IPHONE_B = {"mogaf": {"mpsnr": 18.987654, "mssim": 0.701111, "mlpips": 0.300049, "psnr": 17.5, "ssim": 0.65, "lpips": 0.35}}
DNERF_C = {"mogaf": {"psnr": 22.25, "ssim": 0.912345, "lpips": 0.081234},
           "ode": {"psnr": 21.5, "ssim": 0.9, "lpips": 0.09}}


@pytest.fixture
def metrics_files(tmp_path) -> list[Path]:
    ode_params = {**defaults("ode"), "epochs": 20}
    return [
        write_metrics(tmp_path / "iphone/a/metrics.json", dataset="iphone", scene="a", ratio=0.6, protocol="iphone",
                      methods={m: method_section(v, method=m, wall=100.0 + i, epe=0.1 * (i + 1)) for i, (m, v) in enumerate(IPHONE_A.items())}),
        write_metrics(tmp_path / "iphone/b/metrics.json", dataset="iphone", scene="b", ratio=0.6, protocol="iphone",
                      methods={"mogaf": method_section(IPHONE_B["mogaf"], method="mogaf", wall=210.4)}),
        write_metrics(tmp_path / "dnerf/c/metrics.json", dataset="dnerf", scene="c", ratio=0.8, protocol="dnerf",
                      methods={"mogaf": method_section(DNERF_C["mogaf"], method="mogaf", wall=50.0),
                               "ode": method_section(DNERF_C["ode"], method="ode", wall=75.6, params=ode_params)}),
    ]


def md_rows(md: str) -> list[list[str]]:
    rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in md.splitlines() if line.startswith("|")]
    return [r for r in rows if not all(set(c) <= {"-"} for c in r)]


# ------------------------------------------------------------------ tables
def test_write_tables_writes_every_format(metrics_files, tmp_path):
    outs = main_table_paths(tmp_path / "tables")
    assert len(outs) == 3 * len(TABLE_NAMES)
    written = write_tables([str(p) for p in metrics_files], outs, {}, ABLATIONS)
    assert sorted(map(str, written)) == sorted(outs)
    for name in TABLE_NAMES:
        md = Path(tmp_path / "tables" / f"table_{name}.md").read_text()
        tex = Path(tmp_path / "tables" / f"table_{name}.tex").read_text()
        rows = list(csv.reader(io.StringIO(Path(tmp_path / "tables" / f"table_{name}.csv").read_text())))
        assert md.startswith("### ") and md.endswith("\n")
        assert tex.startswith(r"\begin{table}") and r"\end{tabular}" in tex and tex.count(r"\\") >= 2
        assert rows and all(len(r) == len(rows[0]) for r in rows)
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
    # scene b has no frozen result
    assert b[2:] == ["18.99", "0.7011", "0.3000", NO_RESULT, NO_RESULT, NO_RESULT]
    # averages: means of the rows' values (the missing cell is left out)
    assert avg[2] == f"{(17.123456 + 18.987654) / 2:.2f}"
    assert avg[3] == f"{(0.612345 + 0.701111) / 2:.4f}"
    assert avg[4] == f"{(0.351234 + 0.300049) / 2:.4f}"
    assert avg[5:] == ["15.50", "0.5500", "0.4200"]
    md = t.markdown()
    assert "| 60% | iphone/b | 18.99 | 0.7011 | 0.3000 | no result | no result | no result |" in md
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
    assert mogaf_a[5:] == [fmt(16.5, "psnr"), fmt(0.6, "ssim"), fmt(0.4, "lpips"), fmt(17.123456, "mpsnr"), "0.100", "100"]
    assert by[("b", METHOD_LABELS["mogaf"])][-2:] == [NO_RESULT, "210"]  # no tracking; 210.4 s to 0 digits
    ode_c = by[("c", METHOD_LABELS["ode"] + "*")]
    assert ode_c[5:] == ["21.50", "0.9000", "0.0900", NO_RESULT, NO_RESULT, "76"]
    assert any("epochs (default 40) = 20" in n for n in t.notes)


def test_gcn_off_defaults_is_marked(tmp_path):
    gcn = {**defaults("gcn"), "epochs": 20, "num_threads": 4}
    f = write_metrics(tmp_path / "m.json", dataset="d", scene="s", ratio=0.8, protocol="dnerf",
                      methods={"gcn": method_section({"psnr": 20.0, "ssim": 0.9, "lpips": 0.1}, method="gcn", wall=10.0, params=gcn)})
    t = dnerf_table(load_metrics([f]))
    assert t.spans[1][0] == METHOD_LABELS["gcn"] + "*"
    note = next(n for n in t.notes if n.startswith("*"))
    assert "epochs (default 2001) = 20" in note
    assert "num_threads" not in note  # a runtime knob, not a budget


def test_gcn_at_defaults_is_not_marked(tmp_path):
    f = write_metrics(tmp_path / "m.json", dataset="d", scene="s", ratio=0.8, protocol="dnerf",
                      methods={"gcn": method_section({"psnr": 20.0, "ssim": 0.9, "lpips": 0.1}, method="gcn", wall=10.0)})
    t = dnerf_table(load_metrics([f]))
    assert t.spans[1][0] == METHOD_LABELS["gcn"]
    assert not any(n.startswith("*") for n in t.notes)


def test_empty_tables_say_no_result(tmp_path):
    tables = build_tables([], ABLATIONS)
    assert set(tables) == set(TABLE_NAMES)
    for name in ("forecast", "grouping", "masking"):
        assert tables[name].rows == []
        assert NO_RESULT in tables[name].markdown() and NO_RESULT in tables[name].latex()


def test_grouping_and_masking_ablation_tables(tmp_path):
    img = lambda x: {"mpsnr": x, "mssim": 0.5, "mlpips": 0.3, "psnr": x - 1, "ssim": 0.5, "lpips": 0.3}  # noqa: E731
    default = write_metrics(tmp_path / "d.json", dataset="iphone", scene="a", ratio=0.6, protocol="iphone",
                            methods={"mogaf": method_section(img(18.0), method="mogaf", wall=10.0)},
                            grouping={"method": "ours", "num_groups": 3, "ari": 0.9, "mean_iou": 0.8})
    gaga = write_metrics(tmp_path / "g.json", dataset="iphone", scene="a", ratio=0.6, protocol="iphone", variant="gaga4d",
                         methods={"mogaf": method_section(img(16.0), method="mogaf", wall=10.0)},
                         grouping={"method": "gaga4d", "num_groups": 5, "ari": 0.5, "mean_iou": 0.4})
    nomask = write_metrics(tmp_path / "n.json", dataset="iphone", scene="a", ratio=0.6, protocol="iphone", variant="no_masking",
                           methods={"mogaf": method_section(img(17.0), method="mogaf", wall=10.0,
                                                            params={**defaults("mogaf"), "masking": False})})
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
    pts = [{"wall_s": w, "psnr": e, "id": i} for i, (w, e) in enumerate([(10, 20.0), (20, 25.0), (30, 22.0), (40, 26.0), (40, 24.0), (5, 19.0)])]
    assert [p["id"] for p in pareto_front(pts, "psnr")] == [5, 0, 1, 3]
    # lower is better for an error such as EPE
    pts = [{"wall_s": w, "epe_3d": e, "id": i} for i, (w, e) in enumerate([(10, 0.5), (20, 0.3), (30, 0.4), (40, 0.1), (20, 0.2)])]
    assert [p["id"] for p in pareto_front(pts, "epe_3d")] == [0, 4, 3]
    assert pareto_front([], "psnr") == []


def _runtime_files(tmp_path: Path) -> list[Path]:
    files = []
    # (variant, mogaf (wall, psnr), frozen (wall, psnr))
    for variant, mg, fz in [("default", (100.0, 20.0), (60.0, 15.0)), ("rt_half", (70.0, 21.0), (40.0, 15.5)),
                            ("rt_fast", (50.0, 18.0), (45.0, 14.0)), ("unrelated", (10.0, 30.0), (10.0, 30.0))]:
        files.append(write_metrics(tmp_path / variant / "metrics.json", dataset="iphone", scene="a", ratio=0.6, protocol="iphone",
                                   variant=variant,
                                   methods={"mogaf": method_section({"psnr": mg[1]}, method="mogaf", wall=mg[0]),
                                            "frozen": method_section({"psnr": fz[1]}, method="frozen", wall=fz[0])}))
    return files


def test_runtime_points_and_report(tmp_path):
    files = _runtime_files(tmp_path)
    params = {"error_metric": "psnr", "runtime_variants": ["rt_half", "rt_fast"]}
    points = collect_points(load_metrics(files), "psnr", params["runtime_variants"])
    assert len(points) == 6 and "unrelated" not in {p["variant"] for p in points}
    out = tmp_path / "report"
    written = write_runtime_report([str(f) for f in files], str(out / "e.csv"), str(out / "e.md"), str(out / "e.png"), params)
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
