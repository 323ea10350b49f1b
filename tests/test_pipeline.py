"""End to end: the whole DAG on a tiny synthetic scene (.test/config.yaml).

One uninterrupted run (forecasts per group), then a second run in a fresh
folder (forecasts per method, .test/per_method.yaml) that is killed
(SIGKILL to Snakemake and its jobs) while reconstruction trains, unlocked and
simply rerun. Checks: every method's metrics, nothing written outside
results/, .snakemake/ and the cache folder (HOME is an empty folder that
must stay so, but for Snakemake's own ~/.cache/snakemake), the killed run leaves no partial artefact and resumes
from the stage checkpoint, and both runs give byte-identical metrics.json
(evaluate.runtime_in_metrics is off in the tiny config: wall times differ
between runs by nature).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from support.browser import BrowserError
from support.paths import REPO

# minutes of work in one module fixture: collected first (tests/conftest.py)
pytestmark = pytest.mark.long(seconds=120)

SNAKEFILE = str(REPO / "Snakefile")
CONFIGS = [str(REPO / "config" / "config.yaml"), str(REPO / ".test" / "config.yaml")]
# the second run forecasts in one job per method (forecast.jobs: per_method), the first per group
PER_METHOD = str(REPO / ".test" / "per_method.yaml")
RATIO = Path("results/synthetic/tiny/ratio0.6")
METHODS = ["mogaf", "mogaf_paper", "gcn", "ode", "constant_velocity", "frozen"]


def _env(work: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("MOGAF_CACHE_DIR", "MOGAF_CORES")}  # the config decides
    env.update(extra)
    env.update(
        HOME=str(work / "home"),
        XDG_CACHE_HOME=str(work / "home" / ".cache"),
        XDG_CONFIG_HOME=str(work / "home" / ".config"),
    )
    return env


def _prepare(work: Path) -> None:
    """An empty work folder whose cache holds what `make setup` made (LPIPS weights, built kernel)."""
    (work / "home").mkdir(parents=True)
    src = REPO / ".cache" / "mogaf"
    for sub in ("lpips", "kernels"):
        if (src / sub).is_dir():
            shutil.copytree(
                src / sub, work / ".cache" / "mogaf" / sub, ignore=shutil.ignore_patterns("*.tar.gz", "*.tmp*")
            )


def _command(*layers: str) -> list[str]:
    return [
        sys.executable,
        "-m",
        "snakemake",
        "-s",
        SNAKEFILE,
        "--cores",
        "2",
        "demo",
        "--configfile",
        *CONFIGS,
        *layers,
    ]


def _run(work: Path, *layers: str, timeout: int = 600, **env: str) -> subprocess.CompletedProcess:
    res = subprocess.run(
        _command(*layers), cwd=work, env=_env(work, **env), capture_output=True, text=True, timeout=timeout
    )
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-6000:]
    return res


def _files(root: Path) -> set[Path]:
    return {p.relative_to(root) for p in root.rglob("*") if p.is_file()}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    first = tmp_path_factory.mktemp("run1")
    _prepare(first)
    before = _files(first)
    _run(first, MOGAF_CORES="1")  # the second run takes idle cores (mogaf.cores)
    # second run: killed during reconstruction, then rerun
    second = tmp_path_factory.mktemp("run2")
    _prepare(second)
    proc = subprocess.Popen(
        _command(PER_METHOD),
        cwd=second,
        env=_env(second),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    checkpoint = second / RATIO / "checkpoints" / "recon.pt"
    deadline = time.monotonic() + 300
    while not checkpoint.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    killed = proc.poll() is None and checkpoint.exists()
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    after_kill = _files(second)
    # A killed Snakemake leaves its lock behind: --unlock, then a plain rerun.
    unlock = subprocess.run(
        _command(PER_METHOD) + ["--unlock"], cwd=second, env=_env(second), capture_output=True, text=True, timeout=120
    )
    assert unlock.returncode == 0, unlock.stderr[-3000:]
    rerun = _run(second, PER_METHOD)
    return {
        "first": first,
        "second": second,
        "before": before,
        "killed": killed,
        "after_kill": after_kill,
        "rerun": rerun,
    }


def test_every_method_has_finite_metrics(runs):
    metrics = json.loads((runs["first"] / RATIO / "metrics.json").read_text())
    assert sorted(metrics["methods"]) == sorted(METHODS)
    for method, section in metrics["methods"].items():
        for key in ("psnr", "ssim", "lpips"):
            value = section["image"][key]
            assert isinstance(value, float) and math.isfinite(value), (method, key, value)
        # the quick 3D check against GT trajectories, computed by evaluation (never by a forecast job)
        assert math.isfinite(section["forecast"]["epe_3d_quick"]), method
        # the structure figures of the forecast (mogaf.forecast.coherence), from the forecast artefact
        assert {"rigid_groups", "rigid_distance_change", "still_displacement"} <= set(
            section["forecast"]["coherence"]
        ), method
    # the default MoGaF records its per-group decision; the paper's mode runs beside it
    (job,) = metrics["methods"]["mogaf"]["forecast"]["jobs"].values()
    choices = job.get("part_choices", job["choice"]).split()  # a non-rigid group: each rigid part's own choice
    assert job["mode"] == "structured" and set(choices) <= {"learned", "linear_trend", "constant_velocity", "frozen"}, (
        choices
    )
    assert metrics["methods"]["mogaf_paper"]["forecast"]["params"]["mode"] == "paper"
    # a plausible image score (the end-to-end budgets are too small to rank the methods)
    assert metrics["methods"]["mogaf"]["image"]["psnr"] > 10
    # grouping quality at held-out views (grouping_quality stage), copied into metrics.json
    grouping = metrics["grouping"]
    assert 0.0 <= grouping["mean_iou"] <= 1.0 and math.isfinite(grouping["ari"])
    assert len(grouping["per_object_iou"]) == len(grouping["object_names"]) > 0
    # the model's quality at held-out views (reconstruction_quality stage), copied too
    reconstruction = metrics["reconstruction"]
    assert reconstruction["num_frames"] > 0 and reconstruction["heldout_observed"]["psnr"] > 10


def test_videos_show_every_method_beside_the_ground_truth(runs):
    import imageio.v2 as iio2

    renders = runs["first"] / RATIO / "renders"
    for name in METHODS + ["all_methods"]:
        videos = [p for p in (renders / f"{name}.mp4", renders / f"{name}.gif") if p.exists()]
        assert videos, name
    video = next(p for p in (renders / "all_methods.mp4", renders / "all_methods.gif") if p.exists())
    frame = np.asarray(iio2.mimread(video, memtest=False)[0])[..., :3]
    one = np.asarray(
        iio2.mimread(next(p for p in (renders / "frozen.mp4", renders / "frozen.gif") if p.exists()), memtest=False)[0]
    )
    # GT plus one panel per method, side by side: (1 + len(METHODS)) / 3 as wide as a GT | method | error video
    assert abs(frame.shape[1] / one.shape[1] - (1 + len(METHODS)) / 3) < 0.05


def test_artefacts_record_their_lineage(runs):
    from mogaf.artefact import read_lineage

    ratio = runs["first"] / RATIO
    lineage = {
        name: read_lineage(ratio / name) for name in ("split.h5", "priors.h5", "recon.h5", "groups.h5", "refined.h5")
    }
    scene = read_lineage(runs["first"] / RATIO.parent / "scene.h5")
    assert lineage["priors.h5"].inputs == {"ingest": (scene.digest,), "split": (lineage["split.h5"].digest,)}
    refined = lineage["refined.h5"].inputs
    assert refined["recon"] == (lineage["recon.h5"].digest,) and refined["group"] == (lineage["groups.h5"].digest,)
    quality = read_lineage(ratio / "grouping_quality.h5").inputs
    assert quality["recon"] == (lineage["recon.h5"].digest,) and quality["group"] == (lineage["groups.h5"].digest,)
    # the reconstruction quality is of the model the forecasts start from
    assert read_lineage(ratio / "reconstruction_quality" / "refined.h5").inputs["refine"] == (
        lineage["refined.h5"].digest,
    )
    forecast = read_lineage(ratio / "forecast" / "mogaf.h5")
    assert forecast.inputs["refine"] == (lineage["refined.h5"].digest,)


def test_both_job_layouts_ran(runs):
    """The first run forecast per group (forecast_group jobs, merged), the
    second per method (.test/per_method.yaml: no forecast_group job, each
    trained method's merge job trained its one job 'all'); their metrics.json
    are the same to the byte (test_rerun_after_kill_is_byte_identical)."""
    from mogaf.artefact import read_attrs

    first, second = runs["first"] / RATIO, runs["second"] / RATIO
    assert len(list((first / "forecast").glob("*/groupall.h5"))) == 4
    assert not list((second / "logs").glob("forecast_*_group*.log"))
    assert not list((second / "forecast").glob("*/group*.h5"))
    for method in ("mogaf", "gcn"):
        attrs = read_attrs(second / "forecast" / f"{method}.h5")
        assert attrs["job_layout"] == "per_method" and attrs["num_groups_trained"] == 1, attrs
        assert set(attrs["flags"]) == {"all"}
        assert read_attrs(first / "forecast" / f"{method}.h5")["job_layout"] == "per_group"


def test_writes_only_results_snakemake_and_cache(runs):
    work = runs["first"]
    new = _files(work) - runs["before"]
    allowed = (("results",), (".snakemake",), (".cache", "mogaf"))
    outside = sorted(str(p) for p in new if not any(p.parts[: len(a)] == a for a in allowed))
    assert not outside, outside
    # HOME may only hold Snakemake's own source cache (~/.cache/snakemake), like .snakemake/ its own.
    home = work / "home"
    elsewhere = sorted(
        str(p.relative_to(home))
        for p in home.rglob("*")
        if p.is_file() and p.relative_to(home).parts[:2] != (".cache", "snakemake")
    )
    assert not elsewhere, elsewhere


def test_killed_run_leaves_no_partial_artefact_and_resumes(runs):
    assert runs["killed"], "the run ended before reconstruction wrote its first checkpoint"
    partial = [p for p in runs["after_kill"] if p.name == "recon.h5" or ".tmp" in p.name]
    assert not partial, partial
    log = (runs["second"] / RATIO / "logs" / "recon.log").read_text()
    assert "resumed from" in log, log[-2000:]


def test_rerun_after_kill_is_byte_identical(runs):
    # also across the job layouts: the second run forecast per method
    a = (runs["first"] / RATIO / "metrics.json").read_bytes()
    b = (runs["second"] / RATIO / "metrics.json").read_bytes()
    assert a == b


def _evaluate_again(runs, out: Path, methods, **params) -> bytes:
    """The first run's forecasts of `methods` evaluated again into `out`
    (metrics.json, renders/), evaluate's settings changed by `params`; the
    new metrics.json."""
    import yaml

    from mogaf.config import deep_merge, with_defaults
    from mogaf.stages import evaluate

    ratio = runs["first"] / RATIO
    config = with_defaults(deep_merge(*(yaml.safe_load(Path(c).read_text()) for c in CONFIGS)))
    evaluate(
        scene=str(ratio.parent / "scene.h5"),
        split=str(ratio / "split.h5"),
        model=str(ratio / "refined.h5"),
        groups=str(ratio / "groups.h5"),
        reconstruction_quality=str(ratio / "reconstruction_quality" / "refined.h5"),
        grouping_quality=str(ratio / "grouping_quality.h5"),
        forecasts={m: str(ratio / "forecast" / f"{m}.h5") for m in methods},
        benchmarks={},
        out_metrics=str(out / "metrics.json"),
        out_renders=str(out / "renders"),
        params={**config["evaluate"], **params},
        variant="default",
        ids={"dataset": "synthetic", "scene": "tiny"},
    )
    return (out / "metrics.json").read_bytes()


def test_evaluating_forecasts_side_by_side_writes_the_same_files(runs, tmp_path, monkeypatch):
    """The first run evaluated on one core; its forecasts evaluated again with
    three measured at once (MOGAF_CORES=3) give the same metrics.json and
    renders, byte for byte."""
    ratio = runs["first"] / RATIO
    monkeypatch.setenv("MOGAF_CORES", "3")
    assert _evaluate_again(runs, tmp_path, METHODS) == (ratio / "metrics.json").read_bytes()
    renders = sorted(p for p in _files(ratio / "renders") if p.name != ".snakemake_timestamp")  # Snakemake's own
    assert renders and sorted(_files(tmp_path / "renders")) == renders
    for name in renders:
        assert (tmp_path / "renders" / name).read_bytes() == (ratio / "renders" / name).read_bytes(), name


def test_masked_metrics_without_co_visibility_masks_say_so(runs, tmp_path, monkeypatch):
    """The first run's forecasts evaluated as if its scene had no co-visibility
    masks (as an iPhone capture without DyCheck's masks): mPSNR equals PSNR,
    and metrics.json says why; the first run itself, which has them, says nothing."""
    from mogaf.scene import Scene

    kept = json.loads((runs["first"] / RATIO / "metrics.json").read_text())
    assert kept["protocol"] == "iphone" and "masked_metrics_over" not in kept
    monkeypatch.setattr(Scene, "covisibility_masks", lambda self: None)
    metrics = json.loads(_evaluate_again(runs, tmp_path, ("mogaf", "frozen"), video=False, lpips=False))
    assert metrics["masked_metrics_over"] == "every pixel: the scene has no co-visibility masks"
    for method in ("mogaf", "frozen"):
        image = metrics["methods"][method]["image"]
        assert image["mpsnr"] == pytest.approx(image["psnr"], abs=1e-9)
        assert image["mpsnr"] != kept["methods"][method]["image"]["mpsnr"]
        assert image["psnr"] == kept["methods"][method]["image"]["psnr"]


# ---------------------------------------------------------------- the report, in a real browser
REPORT_CATEGORIES = {"Tables", "Error vs run time", "Forecast videos", "Grouping and reconstruction quality"}
# in a frame (a report page): every video and image loaded, and what the page holds
FRAME_CHECK = """(async () => {
  const media = Array.from(document.querySelectorAll('video, img'));
  await Promise.all(media.map(m => new Promise(ok => {
    if ((m.tagName === 'VIDEO' && m.readyState >= 2) || (m.tagName === 'IMG' && m.complete)) return ok();
    m.addEventListener(m.tagName === 'VIDEO' ? 'loadeddata' : 'load', ok);
    m.addEventListener('error', ok);
    setTimeout(ok, 15000);
  })));
  return {
    videos: Array.from(document.querySelectorAll('video')).map(v => [v.readyState, v.videoWidth, v.error ? v.error.code : 0]),
    images: Array.from(document.querySelectorAll('img')).map(i => [i.complete, i.naturalWidth]),
    tables: Array.from(document.querySelectorAll('table')).map(t => t.rows.length),
    text: document.body.innerText.length,
    links: Array.from(document.querySelectorAll('a[href]')).map(a => a.getAttribute('href')),
  };
})()"""


def _artefact_dir() -> Path:
    """Where the test keeps what a person may want to look at (CI uploads it)."""
    return Path(os.environ.get("MOGAF_TEST_ARTEFACTS", REPO / ".test-artefacts"))


def _open_result(browser, report: Path, category: str, path: str) -> None:
    """Load the report, click the category in its menu, then the result's view
    button (the eye), and wait until the result is shown (a frame or an image
    more than before)."""
    browser.open(report.as_uri())
    found = browser.evaluate(
        f"""(() => {{
          const item = Array.from(document.querySelectorAll('a'))
            .find(e => e.textContent.trim() === {json.dumps(category)});
          if (item) item.click();
          return !!item;
        }})()"""
    )
    assert found, f"no menu entry '{category}'"
    row = f"""Array.from(document.querySelectorAll('td')).find(e => e.textContent.trim() === {json.dumps(path)})"""
    try:
        browser.wait_until(f"!!({row})", timeout=15)
    except BrowserError:
        pytest.fail(f"no row for {path} under '{category}'")
    shown = "document.querySelectorAll('iframe, img').length"
    before = browser.evaluate(shown)
    clicked = browser.evaluate(
        f"""(() => {{
          const cell = {row};
          const eye = cell && cell.closest('tr').querySelector('a[iconname=eye]');
          if (eye) eye.click();
          return !!eye;
        }})()"""
    )
    assert clicked, f"no view button for {path} under '{category}'"
    try:
        browser.wait_until(f"{shown} > {before}", timeout=15)
    except BrowserError:
        pytest.fail(f"{path} under '{category}': its view button showed nothing")


def test_the_report_opens_in_a_browser_with_every_table_figure_and_video(runs):
    """`snakemake --report results/report.zip`, unpacked and opened in headless Chromium:
    every category and result is there, tables have rows, every video and
    image loads, no link is broken and the console stays clean."""
    from support.browser import Browser, find_browser

    executable = find_browser()
    if executable is None:
        pytest.skip("no Chromium on PATH (Debian: apt-get install chromium; .ci/run installs it when it can)")
    import zipfile

    work = runs["first"]
    archive = work / "results" / "report.zip"
    res = subprocess.run(
        _command() + ["--report", str(archive)], cwd=work, env=_env(work), capture_output=True, text=True, timeout=300
    )
    assert res.returncode == 0 and archive.is_file(), res.stderr[-3000:]
    with zipfile.ZipFile(archive) as z:
        z.extractall(work / "results")
    report = work / "results" / "report" / "report.html"
    browser = Browser(executable)
    try:
        browser.open(report.as_uri())
        categories = browser.evaluate("JSON.stringify(window.categories)")
        categories = {name: [p for sub in subs.values() for p in sub] for name, subs in json.loads(categories).items()}
        assert set(categories) == REPORT_CATEGORIES
        seen = {}
        for category, paths in sorted(categories.items()):
            for path in paths:
                _open_result(browser, report, category, path)
                mime = browser.evaluate(f"window.results[{json.dumps(path)}].mime_type")
                if mime == "text/html":  # shown in an iframe
                    frames = browser.child_frames()
                    assert len(frames) == 1, (path, frames)
                    seen[path] = browser.evaluate(FRAME_CHECK, frame=frames[0][0])
                else:  # an image, shown in the page after the report's logo
                    seen[path] = browser.evaluate(FRAME_CHECK)
        videos = [
            v for path, page in seen.items() if path.endswith("/report/videos/index.html") for v in page["videos"]
        ]
        assert len(videos) == 1 + len(METHODS)  # all methods side by side, then one per method
        assert all(state >= 2 and width > 0 and code == 0 for state, width, code in videos), videos
        tables = seen["results/tables/table_forecast.html"]["tables"]
        assert tables and tables[0] >= 1 + len(METHODS), tables  # a header row and a row per method
        figures = [path for path in seen if path.endswith(".png")]
        assert len(figures) == 2 and all(seen[p]["images"][-1] == [True, seen[p]["images"][-1][1]] for p in figures)
        assert all(seen[p]["images"][-1][1] > 100 for p in figures)  # the figure itself, not the 16 px logo
        links = [h for page in seen.values() for h in page["links"]]
        assert all(h.startswith(("#", "data:", "https:", "http:")) for h in links), links  # nothing local to break
        assert browser.problems() == []
        # the page a person looks at first: the forecast videos
        _open_result(browser, report, "Forecast videos", f"{RATIO}/report/videos/index.html")
        browser.evaluate(FRAME_CHECK, frame=browser.child_frames()[0][0])  # its videos loaded
        browser.screenshot(_artefact_dir() / "report_forecast_videos.png")
    finally:
        browser.close()
