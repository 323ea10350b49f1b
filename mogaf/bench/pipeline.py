"""Where the demo's time goes: each job's wall and CPU time against its budget.

    python -m mogaf.bench pipeline                 # read the last `make demo`
    python -m mogaf.bench pipeline --run           # run the demo's DAG afresh first (--forceall)
    python -m mogaf.bench pipeline --results DIR --json rows.json

Reads, under the ratio folder of one scene (default: the demo's), every
job's Snakemake benchmark TSV (wall `s`), its log's "finished in" line (the
stage's own time, torch's import included, and the process's CPU time; the
rest of the job's wall time is Snakemake's script preamble and process
start; without that line, Snakemake's `cpu_time`, sampled every few seconds,
stands for the CPU time), the training loops' phase breakdown
(`time_breakdown_s` of recon.h5 / refined.h5: rasterizer forward and
backward, the rest of the autograd backward, losses, optimiser, density
control) and the forecasters' fit / rollout times. Prints three tables: the
budgets, every job, and the training loops' breakdown, then the shortest
wall time any schedule of these jobs could reach on the given cores (the
longest chain of jobs that wait for each other, and the CPU time shared
over the cores): what speeding up one job can win. Budgets are for an idle
2-core machine; `--run` also times the whole Snakemake run.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import re
import shutil
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from mogaf.artefact import atomic_path
from mogaf.errors import MogafError
from mogaf.forecast.params import METHOD_TABLE
from mogaf.paths import check_writable

DEMO_RESULTS = Path("results/synthetic/default/ratio0.6")
# MoGaF's jobs: the methods reading forecast.mogaf (the method table); the baselines: the others
MOGAF_METHODS = tuple(m.name for m in METHOD_TABLE if "mogaf" in (m.name, m.section))
BASELINE_METHODS = tuple(m.name for m in METHOD_TABLE if m.name not in MOGAF_METHODS)
SNAKEMAKE_BUDGET_S = 180.0

# (row, job-name pattern, budget in s, how jobs combine: "each" = every job within, "sum" = their total)
BUDGETS: list[tuple[str, str, float, str]] = [
    ("recon", r"recon", 60.0, "each"),
    ("refine", r"refine", 20.0, "each"),
    (
        "rigid_init + group + quality stages",
        r"rigid_init|group|grouping_quality|reconstruction_quality_\w+",
        10.0,
        "sum",
    ),
    ("MoGaF forecast job", rf"forecast_({'|'.join(MOGAF_METHODS)})(_group\w+)?", 10.0, "each"),
    ("baseline forecast job", rf"forecast_({'|'.join(BASELINE_METHODS)})(_group\w+)?", 15.0, "each"),
    ("evaluate", r"evaluate", 20.0, "each"),
]

# What each job waits for (patterns over job names of the same run; a sweep
# without a job of its own, e.g. priors, waits for the run's). Forecast merge
# jobs also wait for their own per-group jobs.
NEEDS: list[tuple[str, tuple[str, ...]]] = [
    (r"priors", (r"ingest",)),
    (r"recon", (r"priors",)),
    (r"group", (r"recon",)),
    (r"rigid_init", (r"group",)),
    (r"refine", (r"group", r"rigid_init")),
    (r"grouping_quality", (r"group",)),
    (r"reconstruction_quality_\w+", (r"recon", r"refine")),
    (r"forecast_\w+", (r"group", r"rigid_init", r"refine")),
    (r"evaluate", (r"forecast_\w+", r"grouping_quality", r"reconstruction_quality_\w+")),
]

FINISHED = re.compile(r"finished in ([0-9.]+) s(?:, process CPU ([0-9.]+) s)?")


@dataclass
class Job:
    name: str  # the benchmark file's stem, e.g. "forecast_mogaf_group0"
    sweep: str  # "" for the run itself, else the ablation variant
    wall_s: float
    cpu_s: float | None  # the process's CPU time (its log), else Snakemake's sampled cpu_time
    own_s: float | None = None  # the stage's own time (its log's "finished in")
    detail: dict[str, float] = field(default_factory=dict)

    @property
    def start_s(self) -> float | None:
        """Process start and Snakemake's script preamble: the job's wall time outside the stage."""
        return None if self.own_s is None else max(0.0, self.wall_s - self.own_s)


def _float(value: Any) -> float | None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if v == v else None


def read_tsv(path: Path) -> tuple[float, float | None]:
    """(wall s, CPU s) of a Snakemake benchmark TSV (its last row)."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh, delimiter="\t"))
    if not rows or _float(rows[-1].get("s")) is None:
        raise ValueError(f"{path}: not a Snakemake benchmark TSV (no 's' column)")
    return float(rows[-1]["s"]), _float(rows[-1].get("cpu_time"))


def _own_times(log: Path) -> tuple[float | None, float | None]:
    """(the stage's wall s, the process's CPU s) from the log's last "finished in" line."""
    if not log.is_file():
        return None, None
    found = FINISHED.findall(log.read_text(errors="replace"))
    if not found:
        return None, None
    wall, cpu = found[-1]
    return float(wall), (float(cpu) if cpu else None)


def _job(name: str, sweep: str, tsv: Path, log: Path, detail: dict[str, float]) -> Job:
    """CPU time from the job's own log where it states it: Snakemake samples
    cpu_time every few seconds, so for short jobs its figure is a lower bound."""
    wall, sampled_cpu = read_tsv(tsv)
    own, cpu = _own_times(log)
    return Job(name, sweep, wall, cpu if cpu is not None else sampled_cpu, own, detail)


def _attrs(path: Path) -> dict[str, Any]:
    from mogaf.artefact import read_attrs

    return read_attrs(path) if path.is_file() else {}


def _detail(folder: Path, name: str) -> dict[str, float]:
    """The stage's own breakdown, where its artefact records one."""
    if name in ("recon", "refine"):
        attrs = _attrs(folder / ("recon.h5" if name == "recon" else "refined.h5"))
        return {k: float(v) for k, v in (attrs.get("time_breakdown_s") or {}).items()}
    m = re.fullmatch(r"forecast_(\w+?)_group(\w+)", name)
    if m:
        info = _attrs(folder / "forecast" / m.group(1) / f"group{m.group(2)}.h5").get("info") or {}
        return {k: float(info[k]) for k in ("train_time_s", "rollout_time_s") if k in info}
    m = re.fullmatch(r"forecast_(\w+)", name)
    attrs = _attrs(folder / "forecast" / f"{m.group(1)}.h5") if m else {}
    if attrs.get("job_layout") == "per_method":  # the merge job ran every group: their sums
        out: dict[str, float] = {}
        for info in (attrs.get("flags") or {}).values():
            for k in ("train_time_s", "rollout_time_s"):
                if k in info:
                    out[k] = out.get(k, 0.0) + float(info[k])
        return out
    return {}


def collect(results: Path) -> list[Job]:
    """Every job with a benchmark TSV under `results` (a ratio folder) and its sweeps."""
    if not (results / "benchmarks").is_dir():
        raise FileNotFoundError(f"{results}: no benchmarks/ folder (run `make demo` or pass --run)")
    folders = [("", results)] + [(p.name, p) for p in sorted((results / "ablation").glob("*")) if p.is_dir()]
    scene = results.parent
    jobs: list[Job] = []
    ingest = scene / "benchmarks" / "ingest.tsv"
    if ingest.is_file():
        jobs.append(_job("ingest", "", ingest, scene / "logs" / "ingest.log", {}))
    for sweep, folder in folders:
        for tsv in sorted((folder / "benchmarks").glob("*.tsv")):
            name = tsv.stem
            jobs.append(_job(name, sweep, tsv, folder / "logs" / f"{name}.log", _detail(folder, name)))
    if not jobs:
        raise FileNotFoundError(
            f"{results}: its benchmarks/ folder holds no job's .tsv (run `make demo` or pass --run)"
        )
    return jobs


def budget_rows(jobs: list[Job], snakemake_s: float | None) -> list[dict[str, Any]]:
    rows = []
    for label, pattern, budget, how in BUDGETS:
        sel = [j for j in jobs if not j.sweep and re.fullmatch(pattern, j.name)]
        if not sel:
            continue
        cpu = [j.cpu_s for j in sel if j.cpu_s is not None]
        if how == "sum":
            wall, cpu_v, worst = sum(j.wall_s for j in sel), (sum(cpu) if cpu else None), ""
        else:
            top = max(sel, key=lambda j: j.wall_s)
            wall, cpu_v, worst = top.wall_s, top.cpu_s, top.name if len(sel) > 1 else ""
        rows.append(
            {"row": label, "jobs": len(sel), "wall_s": wall, "cpu_s": cpu_v, "budget_s": budget, "worst": worst}
        )
    if snakemake_s is not None:
        rows.append(
            {"row": "Snakemake run (whole demo)", "jobs": len(jobs), "wall_s": snakemake_s, "cpu_s": None,
             "budget_s": SNAKEMAKE_BUDGET_S, "worst": ""}
        )  # fmt: skip
    for r in rows:
        r["within"] = r["wall_s"] <= r["budget_s"]
    return rows


def _needs(job: Job, jobs: list[Job]) -> list[Job]:
    patterns = next((deps for pattern, deps in NEEDS if re.fullmatch(pattern, job.name)), ())
    own = [j for j in jobs if j.sweep == job.sweep]
    needed = []
    for dep in patterns:
        match = [j for j in own if re.fullmatch(dep, j.name)] or [
            j for j in jobs if not j.sweep and re.fullmatch(dep, j.name)
        ]
        needed += [j for j in match if j is not job]
    if job.name.startswith("forecast_") and "_group" not in job.name:  # a merge waits for its group jobs
        needed += [j for j in own if j.name.startswith(job.name + "_group")]
    return needed


def schedule_bound(jobs: list[Job], cores: int) -> dict[str, Any]:
    """The shortest wall time any schedule of these jobs (their measured wall
    and CPU times) could reach on `cores` cores: the longer of the critical
    path (the longest chain of jobs that wait for each other, NEEDS) and the
    jobs' CPU time shared over the cores."""
    finish: dict[int, float] = {}
    before: dict[int, Job | None] = {}

    def end(job: Job) -> float:
        key = id(job)
        if key not in finish:
            finish[key] = float("nan")  # a cycle would show as nan
            deps = _needs(job, jobs)
            last = max(deps, key=end, default=None)
            before[key] = last
            finish[key] = job.wall_s + (end(last) if last is not None else 0.0)
        return finish[key]

    tail = max(jobs, key=end)
    chain = [tail]
    while before[id(chain[-1])] is not None:
        chain.append(before[id(chain[-1])])
    cpu = sum(j.cpu_s if j.cpu_s is not None else j.wall_s for j in jobs)
    critical = end(tail)
    return {
        "cores": cores,
        "critical_path_s": critical,
        "critical_path": [(j.name, j.sweep) for j in reversed(chain)],
        "cpu_per_core_s": cpu / cores,
        "bound_s": max(critical, cpu / cores),
    }


def schedule_line(bound: dict[str, Any], snakemake_s: float | None) -> str:
    """`schedule_bound`'s result as a sentence (and the run's own wall time, if known)."""
    chain = " -> ".join(f"{name} ({sweep})" if sweep else name for name, sweep in bound["critical_path"])
    cores = bound["cores"]
    return (
        f"No schedule of these jobs on {cores} cores takes less than {bound['bound_s']:.0f} s: "
        f"the critical path takes {bound['critical_path_s']:.0f} s ({chain}), "
        f"the CPU time over {cores} cores {bound['cpu_per_core_s']:.0f} s"
        + ("" if snakemake_s is None else f"; the run took {snakemake_s:.0f} s")
    )


def _s(v: float | None) -> str:
    return "" if v is None else f"{v:.1f}"


def render(jobs: list[Job], rows: list[dict[str, Any]]) -> str:
    out = ["Budgets (idle 2-core machine; 'each': the slowest job of the row)", ""]
    out += ["| row | jobs | wall (s) | CPU (s) | budget (s) | within | slowest |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(
            f"| {r['row']} | {r['jobs']} | {_s(r['wall_s'])} | {_s(r['cpu_s'])} | {r['budget_s']:.0f} | "
            f"{'yes' if r['within'] else 'NO'} | {r['worst']} |"
        )
    total_wall = sum(j.wall_s for j in jobs)
    total_cpu = sum(j.cpu_s or 0.0 for j in jobs)
    out += ["", f"Jobs: {len(jobs)}, wall {total_wall:.0f} s and CPU {total_cpu:.0f} s summed over jobs", ""]
    out += ["| job | sweep | wall (s) | CPU (s) | stage (s) | process start (s) | inside the stage (s) |"]
    out += ["|---|---|---|---|---|---|---|"]
    for j in jobs:
        inside = ", ".join(f"{k.removesuffix('_s')} {v:.1f}" for k, v in j.detail.items() if k != "steps_total")
        out.append(
            f"| {j.name} | {j.sweep} | {_s(j.wall_s)} | {_s(j.cpu_s)} | {_s(j.own_s)} | {_s(j.start_s)} | {inside} |"
        )
    loops = [j for j in jobs if j.detail.get("steps_total")]
    if loops:
        out += ["", "Training loops: share of the steps' time", ""]
        keys = [k for k in loops[0].detail if k not in ("steps_total", "init", "training_psnr_and_model")]
        out += ["| job | sweep | steps (s) | " + " | ".join(keys) + " |", "|---" * (3 + len(keys)) + "|"]
        for j in loops:
            steps = j.detail["steps_total"]
            shares = " | ".join(f"{100.0 * j.detail.get(k, 0.0) / steps:.0f} %" for k in keys)
            out.append(f"| {j.name} | {j.sweep} | {steps:.1f} | {shares} |")
    return "\n".join(out)


def import_seconds(python: str = sys.executable) -> dict[str, float]:
    """Wall seconds a fresh interpreter takes to import torch, and mogaf's stage module:
    what every job pays before it does any work."""
    out = {}
    for name, code in (
        ("python", "pass"),
        ("import torch", "import torch"),
        ("import mogaf.stages", "import mogaf.stages"),
    ):
        start = time.perf_counter()
        subprocess.run([python, "-c", code], check=True)
        out[name] = time.perf_counter() - start
    return out


def run_demo(snakemake: str, cores: int) -> float:
    """Runs the demo's DAG from scratch (`make demo`'s command with --forceall) and returns its wall time."""
    cmd = [snakemake, "--cores", str(cores), "demo", "--configfile", "config/config.yaml", "config/demo.yaml"]
    cmd.append("--forceall")
    start = time.perf_counter()
    subprocess.run(cmd, check=True)
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m mogaf.bench pipeline", description=__doc__.split("\n")[0])
    ap.add_argument("--results", type=Path, default=DEMO_RESULTS, help="a ratio folder (default: the demo's)")
    ap.add_argument("--run", action="store_true", help="run the demo's DAG afresh first (recomputes every job)")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--snakemake", default=str(Path(sys.executable).with_name("snakemake")))
    ap.add_argument("--snakemake-seconds", type=float, default=None, help="the whole run's wall time, if known")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = ap.parse_args(argv)
    if args.cores < 1:
        ap.error(f"--cores must be at least 1, got {args.cores}")
    total = args.snakemake_seconds
    if total is not None and not (math.isfinite(total) and total >= 0):
        ap.error(f"--snakemake-seconds must be a finite number >= 0, got {total}")
    if args.run and shutil.which(args.snakemake) is None:
        ap.error(f"--snakemake {args.snakemake}: no such executable (install the workflow extra: `make setup`)")
    try:
        if args.json:
            check_writable(args.json)
        if args.run:
            total = run_demo(args.snakemake, args.cores)
        jobs = collect(args.results)
    except (FileNotFoundError, ValueError, MogafError) as exc:
        print(f"mogaf.bench pipeline: {exc}", file=sys.stderr)
        return 2
    rows = budget_rows(jobs, total)
    print(render(jobs, rows))
    bound = schedule_bound(jobs, args.cores)
    print("\n" + schedule_line(bound, total))
    imports = import_seconds()
    print("\nA fresh process here: " + ", ".join(f"{k} {v:.2f} s" for k, v in imports.items()))
    if args.json:
        payload = {"results": str(args.results), "snakemake_s": total, "budgets": rows,
                   "schedule": bound, "imports_s": imports, "jobs": [asdict(j) for j in jobs]}  # fmt: skip
        try:
            with atomic_path(args.json) as tmp:
                tmp.write_text(json.dumps(payload, indent=1) + "\n")
        except MogafError as exc:
            print(f"mogaf.bench pipeline: {exc}", file=sys.stderr)
            return 2
    return 0
