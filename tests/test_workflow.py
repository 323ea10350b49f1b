"""The Snakemake workflow: lint, DAG shape, one-line errors, profiles, leave-out rules.

Dry runs only (no stage runs here): each takes a few seconds.
"""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from support.paths import REPO

# about 35 s with two workers: collected early (tests/conftest.py)
pytestmark = pytest.mark.long(seconds=35)

SNAKEFILE = str(REPO / "Snakefile")
CONFIG = str(REPO / "config" / "config.yaml")
PAPER = str(REPO / "config" / "paper.yaml")


def snakemake(
    args: list[str], cwd: Path, configfiles: tuple[str, ...] = (CONFIG,), timeout: int = 120
) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "snakemake", "-s", SNAKEFILE, *args, "--configfile", *configfiles]
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout)


def job_counts(output: str) -> dict[str, int]:
    block = output.split("Job stats:", 1)[1].split("total", 1)[0]
    return {m.group(1): int(m.group(2)) for m in re.finditer(r"^(\w+)\s+(\d+)\s*$", block, re.M)}


def job_blocks(output: str, rule: str) -> list[str]:
    """The dry-run description of every job of `rule`."""
    blocks = re.split(r"\n\[[^\]]+\]\n", output)
    return [b for b in blocks if re.match(rf"(local)?(rule|checkpoint) {rule}:", b.strip())]


def test_lint_clean(tmp_path):
    res = snakemake(["--lint"], REPO)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "Congratulations, your workflow is in a good condition!" in res.stdout + res.stderr


def test_default_target_lists_the_chain(tmp_path):
    res = snakemake(["-n", "demo"], tmp_path)
    assert res.returncode == 0, res.stderr
    counts = job_counts(res.stdout)
    for rule in ("synthesize", "ingest", "split", "priors", "recon", "group", "evaluate", "tables", "runtime_report"):
        assert counts.get(rule, 0) >= 1, (rule, counts)
    # The run-time sweep changes reconstruction only: priors and split are shared.
    assert counts["priors"] == 1 and counts["split"] == 1 and counts["recon"] == 3

    def priorities(rule):
        return {int(p) for b in job_blocks(res.stdout, rule) for p in re.findall(r"^\s*priority: (\d+)$", b, re.M)}

    # With more jobs ready than cores, the chain every forecast waits for goes
    # before what only evaluation reads (PRIORITY in common.smk; 0 is not printed).
    assert priorities("recon") == priorities("refine") == {3}
    assert priorities("grouping_quality") == priorities("reconstruction_quality") == {1}
    assert priorities("evaluate") == set()


def test_tables_read_other_configs_results_without_rebuilding_them(tmp_path):
    """A metrics.json of a scene this config does not know (another config's
    run) is read by the tables but is no job of this DAG: forcing evaluate
    (`-R evaluate`) once re-ran it without its config, failed and deleted it."""
    other = tmp_path / "results" / "mujoco" / "scene1" / "ratio0.8" / "metrics.json"
    other.parent.mkdir(parents=True)
    other.write_text("{}")
    res = snakemake(["-n", "demo", "-R", "evaluate"], tmp_path)
    assert res.returncode == 0, res.stderr
    assert "results/mujoco" not in "".join(job_blocks(res.stdout, "evaluate"))
    (tables,) = job_blocks(res.stdout, "tables")
    assert "results/mujoco" not in tables.split("output:")[0]  # not an input


def test_users_example_without_data_fails_fast_in_one_line(tmp_path):
    start = time.perf_counter()
    res = snakemake(["-n", "results/iphone/apple/ratio0.6/metrics.json"], tmp_path)
    elapsed = time.perf_counter() - start
    assert res.returncode != 0
    lines = [line for line in (res.stdout + res.stderr).splitlines() if "data/iphone/apple" in line]
    assert len(lines) == 1, res.stderr
    assert "DyCheck" in lines[0] and "Shape-of-Motion" in lines[0]
    assert elapsed < 60  # seconds, not a hang (Snakemake start-up dominates)
    assert not (tmp_path / "results").exists()


@pytest.mark.parametrize(
    "target, message",
    [
        ("results/nope/x/ratio0.6/metrics.json", "unknown dataset 'nope'"),
        ("results/iphone/nope/ratio0.6/metrics.json", "unknown scene 'nope' of dataset 'iphone'"),
        ("results/synthetic/default/ratio0.6/ablation/nope/metrics.json", "unknown ablation variant 'nope'"),
    ],
)
def test_unknown_names(tmp_path, target, message):
    res = snakemake(["-n", target], tmp_path)
    assert res.returncode != 0
    assert message in res.stdout + res.stderr


def test_a_scene_the_config_lacks_is_one_line_even_with_its_artefacts_on_disk(tmp_path):
    """A family scene's forecast targeted without config/family.yaml: its groups.h5
    (the group checkpoint's output) is on disk, so Snakemake looks no further
    upstream; the forecast job used to start with its inputs unresolved and die
    in a traceback."""
    groups = tmp_path / "results" / "synthetic" / "f00_stop" / "ratio0.6" / "groups.h5"
    groups.parent.mkdir(parents=True)
    groups.write_bytes(b"")
    res = snakemake(["-n", "results/synthetic/f00_stop/ratio0.6/forecast/mogaf.h5"], tmp_path)
    assert res.returncode != 0, res.stdout
    assert "unknown scene 'f00_stop' of dataset 'synthetic'" in res.stdout + res.stderr
    assert "rule forecast:" not in res.stdout


def test_sweep_shares_upstream_stages(tmp_path):
    res = snakemake(["-n", "sweep_groupwise"], tmp_path)
    assert res.returncode == 0, res.stderr
    counts = job_counts(res.stdout)
    # Eight forecaster variants + the default result, one reconstruction, one grouping.
    assert counts["evaluate"] == 9
    assert counts["recon"] == 1 and counts["group"] == 1 and counts["priors"] == 1


def _fake_paper_data(root: Path) -> None:
    import yaml

    paper = yaml.safe_load(Path(PAPER).read_text())
    for entry in paper["grid"]:
        for scene in entry["scenes"]:
            (root / "data" / entry["dataset"] / scene).mkdir(parents=True, exist_ok=True)


def test_slurm_profile_dry_runs_the_paper_grid(tmp_path):
    pytest.importorskip("snakemake_executor_plugin_slurm")
    _fake_paper_data(tmp_path)
    res = snakemake(["-n", "all", "--profile", str(REPO / "profiles" / "slurm")], tmp_path, configfiles=(CONFIG, PAPER))
    assert res.returncode == 0, res.stderr[-3000:]
    counts = job_counts(res.stdout)
    # 5 iPhone + 8 D-NeRF + 5 MuJoCo scenes + the synthetic demo scene.
    assert counts["ingest"] == 19
    # scene x ratio: iPhone 5x4, D-NeRF 8x2, MuJoCo 5x2, demo 1.
    assert counts["split"] == 47 and counts["priors"] == 47
    # + two reconstructions of the demo's run-time sweep.
    assert counts["recon"] == 49
    # + Gaga-4D grouping on the five iPhone scenes.
    assert counts["group"] == 54
    # results: 47 + 8x5 group-wise + 5 grouping + 8 masking + 2 run-time sweep
    assert counts["evaluate"] == 102
    recon = job_blocks(res.stdout, "recon")
    assert len(recon) == 49
    # the profile's sizes (first attempt); the GPU comes from the rule, as device=cuda (the profile's)
    assert all("gpu=1" in b and "mem_mb=4000" in b and "runtime=15" in b for b in recon)
    group = job_blocks(res.stdout, "group")
    assert len(group) == 54 and all("gpu=1" not in b and "mem_mb=1500" in b for b in group)
    assert len(job_blocks(res.stdout, "tables")) == 1


def test_slurm_profile_asks_for_no_gpu_with_device_cpu(tmp_path):
    """`--config device=cpu` (replacing the profile's device=cuda) drops every GPU request."""
    pytest.importorskip("snakemake_executor_plugin_slurm")
    profile = ["--profile", str(REPO / "profiles" / "slurm"), "--config", "device=cpu"]
    res = snakemake(["-n", "demo", *profile], tmp_path, configfiles=(CONFIG, str(REPO / ".test" / "config.yaml")))
    assert res.returncode == 0, res.stderr[-3000:]
    for rule in ("recon", "refine"):
        (block,) = job_blocks(res.stdout, rule)
        assert "gpu=0" in block and "mem_mb=4000" in block, block


def _groups_tree(root: Path, rigid: list[int]) -> None:
    """A results tree up to groups.h5 (placeholder upstream files, real groups.h5)."""
    from mogaf.grouping.core import Groups
    from mogaf.grouping.stage import write_groups

    base = root / "results" / "synthetic" / "default"
    (base / "source").mkdir(parents=True)
    ratio = base / "ratio0.6"
    ratio.mkdir()
    for path in (base / "scene.h5", ratio / "split.h5", ratio / "priors.h5", ratio / "recon.h5"):
        path.write_text("placeholder")
        time.sleep(0.01)  # strictly increasing modification times
    k = len(rigid)
    groups = Groups(
        group_id=np.arange(3 * k) % k,
        rigid=np.asarray(rigid, np.int8),
        static=np.zeros(k, np.int8),
        instance_id=np.arange(1, k + 1),
        names=[f"g{i}" for i in range(k)],
        rigid_source=["label"] * k,
        method="ours",
        params={},
    )
    write_groups(ratio / "groups.h5", groups, digest="d")


def test_sweep_measures_its_shared_grouping_once(tmp_path):
    _groups_tree(tmp_path, [1, 0])  # past the checkpoint, the evaluate jobs' inputs are known
    res = snakemake(["-n", "sweep_groupwise"], tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    counts = job_counts(res.stdout)
    assert counts["evaluate"] == 9 and counts["grouping_quality"] == 1 and counts["reconstruction_quality"] == 2


@pytest.mark.parametrize("rigid, expect", [([0, 0], False), ([1, 0], True)])
def test_rigid_init_runs_only_with_rigid_groups(tmp_path, rigid, expect):
    _groups_tree(tmp_path, rigid)
    res = snakemake(["-n", "results/synthetic/default/ratio0.6/refined.h5"], tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    counts = job_counts(res.stdout)
    assert counts.get("refine") == 1
    assert ("rigid_init" in counts) is expect
    assert "recon" not in counts and "group" not in counts  # existing artefacts are reused


@pytest.mark.parametrize("layout", ["per_group", "per_method"])
def test_forecast_jobs_layout_decides_the_forecast_jobs(tmp_path, layout):
    """forecast.jobs: per_group, a job per dynamic group and trained method;
    per_method, none: the merge job trains (and asks for the GPU on cuda)."""
    _groups_tree(tmp_path, [1, 0])
    layer = tmp_path / "layout.yaml"
    layer.write_text(f"forecast: {{jobs: {layout}}}\ndevice: cuda\n")
    res = snakemake(
        ["-n", "results/synthetic/default/ratio0.6/metrics.json"], tmp_path, configfiles=(CONFIG, str(layer))
    )
    assert res.returncode == 0, res.stderr[-3000:]
    counts = job_counts(res.stdout)
    trained = ("mogaf", "mogaf_paper", "gcn", "ode")
    assert counts.get("forecast_group", 0) == (2 * len(trained) if layout == "per_group" else 0)
    assert counts["forecast"] == 6
    gpus = {
        b.split("output:", 1)[1].split()[0].rsplit("/", 1)[1]: "gpu=1" in b for b in job_blocks(res.stdout, "forecast")
    }
    assert gpus == {
        f"{m}.h5": layout == "per_method" and m in trained for m in (*trained, "constant_velocity", "frozen")
    }
    # where cores are short, the trained forecasts start in forecast.start_first's order
    # (config.yaml: gcn, mogaf_paper, mogaf, ode), below the chain and above evaluation's inputs
    training_rule, base = ("forecast_group", 2) if layout == "per_group" else ("forecast", 1)
    priority = {}
    for b in job_blocks(res.stdout, training_rule):
        priority.setdefault(re.search(r"method=(\w+)", b)[1], set()).add(float(re.search(r"priority: ([\d.]+)", b)[1]))
    assert all(len(p) == 1 for p in priority.values()), priority  # the same for every group of a method
    ranked = sorted(trained, key=lambda m: -min(priority[m]))
    assert ranked == ["gcn", "mogaf_paper", "mogaf", "ode"], priority
    assert all(base < min(priority[m]) < base + 1 for m in trained), priority
    assert all(priority.get(m, {base}) == {base} for m in ("constant_velocity", "frozen")), priority


def test_the_scene_family_runs_every_scene_at_both_ratios_into_one_table(tmp_path):
    family = str(REPO / "config" / "family.yaml")
    res = snakemake(["-n", "scenes"], tmp_path, configfiles=(CONFIG, str(REPO / "config" / "demo.yaml"), family))
    assert res.returncode == 0, res.stderr
    counts = job_counts(res.stdout)
    scenes = len(yaml.safe_load(Path(family).read_text())["synthetic"])
    assert counts["synthesize"] == scenes and counts["split"] == 2 * scenes and counts["recon"] == 2 * scenes
    assert counts["evaluate"] == 2 * scenes and counts["scenes"] == 1
    assert "results/tables/scenes.md" in job_blocks(res.stdout, "scenes")[0]
