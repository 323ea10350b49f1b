"""`make cluster-test`: the suite's tiny demo through profiles/slurm on a real SLURM cluster, checked.

    python scripts/cluster_check.py [--work DIR] [--cancel-rule RULE] [--cancel-match TEXT] [--timeout S]

Needs a running cluster whose commands (sbatch, squeue, sacct, scancel) work
here, e.g. the one-node cluster of scripts/slurm-localhost.sh. In DIR (emptied
first) `local/` runs `snakemake --cores 2 demo` and `slurm/` the same target
with `--profile profiles/slurm`, side by side, both on the tiny config
(.test/config.yaml, a 64x48 synthetic scene) with `--config device=cpu`. Once
a job of RULE (default rigid_init, which runs beside grouping_quality; its
SLURM comment, rule and wildcards, holding TEXT) has run 1 s, it is cancelled
with scancel. That run (`--retries 0`, so the cancellation is not retried)
must fail naming the job; a plain rerun must complete. Checks, printed as a
report:

- every job of the DAG but the `localrules` ran as a SLURM job of its own: a
  SLURM job id in Snakemake's log, a log in the profile's slurm-logdir, and
  sacct reports it COMPLETED (the cancelled one CANCELLED);
- the rerun ran exactly the jobs the first run had not finished; no file of
  the first run was lost, and the outputs, logs and benchmarks of its finished
  jobs were not rewritten (mtime and size);
- metrics.json is byte-identical to the local run's and every HDF5 artefact
  equal array for array (attributes too, but creation times and timings).

Exit status 0 when every check passes, 1 otherwise (a run past --timeout is
killed and counts as failed).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CONFIGS = [str(REPO / "config" / "config.yaml"), str(REPO / ".test" / "config.yaml")]
TARGET = "demo"
METRICS = Path("results/synthetic/tiny/ratio0.6/metrics.json")
MARKER = ".mogaf-cluster-test"
CANCEL_AFTER_S = 1.0  # seconds a job has been RUNNING when it is cancelled
# The plugin checks job states every --slurm-init-seconds-before-status-checks
# seconds (40 by default, +10 each time no job finished): 2 here, so that a
# chain of ~14 short jobs is not mostly waiting. The cancelled run gets no retry.
SLURM_ARGS = ["--profile", str(REPO / "profiles" / "slurm"), "--slurm-init-seconds-before-status-checks", "2"]
SLURM_ARGS += ["--slurm-keep-successful-logs"]
# Attributes that differ between two runs by nature: when a file was written and how long stages took.
VOLATILE_ATTR = re.compile(r"^mogaf_created_utc$|^time_breakdown_s$|(^|_)(time|wall)_s$|(^|_)seconds$")

SUBMITTED = re.compile(r"Job (\d+) has been submitted with SLURM jobid (\d+) \(log: ([^)]+)\)")
FINISHED = re.compile(r"Finished jobid: (\d+) \(Rule: (\w+)\)")
JOB_BLOCK = re.compile(r"^(local)?(?:rule|checkpoint) (\w+):\n((?:    .*\n)+)", re.M)


class Report:
    def __init__(self) -> None:
        self.failures: list[str] = []

    def line(self, text: str = "") -> None:
        print(text, flush=True)

    def check(self, ok: bool, text: str) -> bool:
        self.line(f"  [{'ok' if ok else 'FAIL'}] {text}")
        if not ok:
            self.failures.append(text)
        return ok


def some(items: list[str]) -> str:
    """The first few of `items` for a report line ('' when there are none)."""
    return f": {', '.join(items[:5])}" + (" ..." if len(items) > 5 else "") if items else ""


def run(cmd: list[str], **kw) -> str:
    return subprocess.run(cmd, check=True, capture_output=True, text=True, **kw).stdout


def snakemake_cmd(*extra: str) -> list[str]:
    cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), TARGET, "--configfile", *CONFIGS]
    return cmd + ["--config", "device=cpu", *extra]


def env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k != "MOGAF_CACHE_DIR"}  # the config's cache_dir decides


def prepare(work: Path) -> None:
    """An empty work folder; each run's cache holds what `make setup` made (LPIPS weights, built kernel)."""
    if work.exists():
        if any(work.iterdir()) and not (work / MARKER).exists():
            raise SystemExit(f"cluster_check: {work} is not empty and not a folder this script made: not emptying it")
        shutil.rmtree(work)
    work.mkdir(parents=True)
    (work / MARKER).write_text("scratch folder of scripts/cluster_check.py\n")
    for name in ("local", "slurm"):
        (work / name).mkdir()
        for sub in ("lpips", "kernels"):
            src = REPO / ".cache" / "mogaf" / sub
            if src.is_dir():
                shutil.copytree(src, work / name / ".cache" / "mogaf" / sub, ignore=shutil.ignore_patterns("*.tar.gz"))


def start(cmd: list[str], cwd: Path, log: Path) -> subprocess.Popen:
    with open(log, "w") as fh:
        return subprocess.Popen(cmd, cwd=cwd, env=env(), stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)


def jobs_of(log: str) -> dict[int, tuple[str, str, bool, tuple[str, ...]]]:
    """Snakemake's job id -> (rule, wildcards, local, its output, log and benchmark paths) for every
    job a run's log describes."""
    jobs = {}
    for m in JOB_BLOCK.finditer(log):
        fields = dict(re.findall(r"^    (\w+): (.*)$", m.group(3), re.M))
        if "jobid" in fields:
            paths = ", ".join(fields.get(k, "") for k in ("output", "log", "benchmark")).split(", ")
            jobs[int(fields["jobid"])] = (
                m.group(2),
                fields.get("wildcards", ""),
                bool(m.group(1)),
                tuple(p for p in paths if p),
            )
    return jobs


def under(root: Path, paths: tuple[str, ...]) -> set[Path]:
    """The files among `paths` (relative to root), those in folders included."""
    found: set[Path] = set()
    for path in paths:
        full = root / path
        if full.is_dir():
            found |= {p.relative_to(root) for p in full.rglob("*") if p.is_file()}
        elif full.is_file():
            found.add(Path(path))
    return found


def wait(proc: subprocess.Popen, seconds: float) -> int | None:
    """The exit status, or None after killing the run (and its jobs' local processes) past `seconds`."""
    try:
        return proc.wait(timeout=max(seconds, 1))
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        return None


def cancel_when_running(proc: subprocess.Popen, rule: str, match: str, rep: Report) -> str | None:
    """scancel the first job of `rule` whose comment contains `match`, once it has run
    CANCEL_AFTER_S: still running whatever the rule, since the job's own Snakemake takes
    longer than that to start (a rigid_init job lasts about 4 s in all)."""
    seen = None
    while proc.poll() is None:
        out = subprocess.run(["squeue", "-h", "-o", "%i|%T|%k"], capture_output=True, text=True).stdout
        for line in out.splitlines():
            jobid, state, comment = line.split("|", 2)
            if comment.split("_wildcards_")[0] == f"rule_{rule}" and match in comment and state == "RUNNING":
                seen = seen or (jobid, time.monotonic())
        if seen and time.monotonic() - seen[1] >= CANCEL_AFTER_S:
            run(["scancel", seen[0]])
            rep.line(f"  scancel {seen[0]} ({rule}) after {time.monotonic() - seen[1]:.0f} s RUNNING")
            return seen[0]
        time.sleep(0.5)
    return None


def sacct(ids: list[str]) -> dict[str, dict[str, str]]:
    """JobID -> State, Elapsed, ReqTRES, Comment, and MaxRSS over the job's steps."""
    fields = ["JobID", "State", "ExitCode", "Elapsed", "ReqTRES", "Comment", "MaxRSS"]
    out = run(["sacct", "-n", "-P", "-j", ",".join(ids), "-o", ",".join(fields)])
    rows: dict[str, dict[str, str]] = {}
    for line in out.splitlines():
        row = dict(zip(fields, line.split("|")))
        main, _, step = row["JobID"].partition(".")
        if not step:
            rows[main] = row | {"MaxRSS": ""}
        elif main in rows and row["MaxRSS"]:
            rows[main]["MaxRSS"] = max(rows[main]["MaxRSS"], row["MaxRSS"], key=_kib)
    return rows


def _kib(text: str) -> float:
    units = {"K": 1, "M": 1024, "G": 1024**2}
    return float(text[:-1]) * units[text[-1]] if text and text[-1] in units else float(text or 0) / 1024


def tres(text: str, key: str) -> str:
    return dict(kv.split("=", 1) for kv in text.split(",") if "=" in kv).get(key, "-")


def files(root: Path) -> dict[Path, tuple[int, int]]:
    """Every file under results/ -> (mtime_ns, size)."""
    return {
        p.relative_to(root): (p.stat().st_mtime_ns, p.stat().st_size)
        for p in (root / "results").rglob("*")
        if p.is_file()
    }


def _stable(value):
    """An attribute value without the parts that differ between runs by nature (timings, creation time)."""
    if isinstance(value, bytes):
        value = value.decode()
    if isinstance(value, str) and value.startswith("json:"):
        value = json.loads(value[5:])
    if isinstance(value, dict):
        return {k: _stable(v) for k, v in value.items() if not VOLATILE_ATTR.search(k)}
    if isinstance(value, list):
        return [_stable(v) for v in value]
    if hasattr(value, "tolist"):
        return value.tolist()
    return value


def compare_h5(a: Path, b: Path) -> tuple[int, list[str]]:
    """(number of arrays compared, differences) between two HDF5 files."""
    import h5py
    import numpy as np

    diffs: list[str] = []
    count = 0
    with h5py.File(a, "r") as fa, h5py.File(b, "r") as fb:
        names_a: list[str] = []
        names_b: list[str] = []
        fa.visit(names_a.append)
        fb.visit(names_b.append)
        if sorted(names_a) != sorted(names_b):
            diffs.append(f"{a.name}: different members {sorted(set(names_a) ^ set(names_b))[:5]}")
        for name in ["/", *names_a]:
            if name not in fb:
                continue
            oa, ob = fa[name], fb[name]
            for key in sorted(set(oa.attrs) | set(ob.attrs)):
                if VOLATILE_ATTR.search(key):
                    continue
                va = _stable(oa.attrs[key]) if key in oa.attrs else None
                vb = _stable(ob.attrs[key]) if key in ob.attrs else None
                if va != vb:
                    diffs.append(f"{name} attribute {key}")
            if isinstance(oa, h5py.Dataset):
                count += 1
                xa, xb = oa[()], ob[()]
                same = xa.dtype == xb.dtype and np.shape(xa) == np.shape(xb)
                if same:
                    nan = xa.dtype.kind in "fc"
                    same = np.array_equal(xa, xb, equal_nan=nan)
                if not same:
                    diffs.append(f"{name} array")
    return count, diffs


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--work", type=Path, default=Path("/tmp/mogaf-cluster-test"))
    parser.add_argument(
        "--cancel-rule", default="rigid_init", help="the rule whose job is cancelled (default: %(default)s)"
    )
    parser.add_argument("--cancel-match", default="", help="text its SLURM comment (rule and wildcards) must hold")
    parser.add_argument("--timeout", type=float, default=900, help="seconds for the SLURM run and rerun together")
    args = parser.parse_args()
    rep = Report()
    t0 = time.monotonic()
    work = args.work.resolve()
    what = args.cancel_rule + (f" ({args.cancel_match})" if args.cancel_match else "")

    node = run(["sinfo", "-h", "-N", "-o", "%N %c CPUs, %m MB, %T"]).strip()
    rep.line(f"cluster-test: node {node} (sinfo); work folder {work}")
    prepare(work)
    local_dir, slurm_dir = work / "local", work / "slurm"

    # 1. the reference (local) and the SLURM run side by side; one SLURM job cancelled mid-run
    rep.line(f"[1] `snakemake {TARGET}` on the tiny config: locally (--cores 2) and with --profile profiles/slurm")
    local = start(snakemake_cmd("--cores", "2"), local_dir, work / "local.log")
    first = start(snakemake_cmd(*SLURM_ARGS, "--retries", "0"), slurm_dir, work / "slurm-1.log")
    cancelled = cancel_when_running(first, args.cancel_rule, args.cancel_match, rep)
    first_rc = wait(first, args.timeout - (time.monotonic() - t0))
    first_s = time.monotonic() - t0
    log1 = (work / "slurm-1.log").read_text()
    rep.line(f"  SLURM run 1: exit status {first_rc} after {first_s:.0f} s")
    rep.check(cancelled is not None, f"a {what} job was RUNNING and was cancelled")
    rep.check(
        first_rc not in (0, None)
        and f"Error in rule {args.cancel_rule}" in log1
        and f"SLURM-job '{cancelled}' failed, SLURM status is: 'CANCELLED'" in log1,
        f"Snakemake reported the cancelled job {cancelled} as failed (CANCELLED) and exited non-zero",
    )
    after_first = files(slurm_dir)

    # 2. the rerun: the profile as a user runs it
    t2 = time.monotonic()
    rerun = start(snakemake_cmd(*SLURM_ARGS), slurm_dir, work / "slurm-2.log")
    rerun_rc = wait(rerun, args.timeout - (time.monotonic() - t0))
    rerun_s = time.monotonic() - t2
    log2 = (work / "slurm-2.log").read_text()
    rep.line(f"[2] rerun: exit status {rerun_rc} after {rerun_s:.0f} s")
    rep.check(rerun_rc == 0, "the rerun completed")
    local_rc = wait(local, 120)
    rep.check(local_rc == 0, "the local run completed")
    if rerun_rc != 0 or local_rc != 0 or cancelled is None:
        for name in ("slurm-1.log", "slurm-2.log", "local.log"):
            rep.line(f"--- tail of {work / name}\n" + (work / name).read_text()[-3000:])
        rep.line(f"cluster-test FAILED ({time.monotonic() - t0:.0f} s): " + "; ".join(rep.failures))
        return 1

    jobs1, jobs2 = jobs_of(log1), jobs_of(log2)
    finished1 = [jobs1[int(j)] for j, _ in FINISHED.findall(log1)]
    done1 = {j[:2] for j in finished1}
    ran2 = {jobs2[int(j)][:2] for j, _ in FINISHED.findall(log2)}
    dag = {v[:2] for v in jobs1.values()} | {v[:2] for v in jobs2.values()}
    rep.check(
        not (done1 & ran2) and done1 | ran2 == dag,
        f"the rerun ran what run 1 had not finished, nothing else: {len(ran2)} jobs "
        f"({', '.join(sorted({r for r, _ in ran2}))}); run 1 had finished {len(done1)} of {len(dag)}",
    )
    after_rerun = files(slurm_dir)
    lost = sorted(str(p) for p in after_first if p not in after_rerun)
    kept = set().union(*(under(slurm_dir, j[3]) for j in finished1))
    changed = sorted(str(p) for p in kept if after_rerun.get(p) != after_first.get(p))
    rep.check(not lost, f"no file of run 1 lost ({len(after_first)} files){some(lost)}")
    rep.check(
        not changed and len(kept) > 0,
        f"the {len(kept)} outputs, logs and benchmarks of run 1's finished jobs untouched (mtime, size){some(changed)}",
    )

    # 3. one SLURM job per DAG job, COMPLETED in sacct
    submitted = [(jobs1, s) for s in SUBMITTED.findall(log1)] + [(jobs2, s) for s in SUBMITTED.findall(log2)]
    ids = [sid for _, (_, sid, _) in submitted]
    states = sacct(ids)
    local_keys = {v[:2] for v in (*jobs1.values(), *jobs2.values()) if v[2]}
    remote = dag - local_keys
    rep.line(f"[3] SLURM jobs: {len(ids)} submitted (sacct; cpus and mem as requested, maxrss as used)")
    rep.line(f"  {'jobid':>6}  {'state':<10} {'elapsed':>8} {'cpus':>4} {'mem':>6} {'maxrss':>7}  rule")
    completed: Counter = Counter()
    for jobs, (snake_id, sid, slurm_log) in submitted:
        rule, wildcards, _, _ = jobs[int(snake_id)]
        row = states.get(sid, {})
        state = row.get("State", "missing").split()[0]
        if state == "COMPLETED":
            completed[(rule, wildcards)] += 1
        wc = ", ".join(w for w in wildcards.split(", ") if w.split("=")[0] in ("method", "group", "model"))
        req = row.get("ReqTRES", "")
        rss = f"{_kib(row['MaxRSS']) / 1024:.0f}M" if row.get("MaxRSS") else "-"
        rep.line(
            f"  {sid:>6}  {state:<10} {row.get('Elapsed', ''):>8} {tres(req, 'cpu'):>4} "
            f"{tres(req, 'mem'):>6} {rss:>7}  {rule}" + (f" ({wc})" if wc else "")
        )
        expected = "CANCELLED" if sid == cancelled else "COMPLETED"
        comment_rule = row.get("Comment", "").split("_wildcards_")[0]
        if state != expected or comment_rule != f"rule_{rule}" or not Path(slurm_log).is_file():
            rep.check(False, f"SLURM job {sid} ({rule}): {state}, expected {expected}, with its log {slurm_log}")
    rep.check(
        len(set(ids)) == len(ids) and all(completed[k] == 1 for k in remote) and sum(completed.values()) == len(remote),
        f"each of the {len(remote)} non-local jobs of the DAG ran as a SLURM job of its own, COMPLETED, with its "
        f"log in results/logs/slurm/ (local by design: {', '.join(sorted({k[0] for k in local_keys}))})",
    )

    # 4. the same artefacts as the local run
    rep.line("[4] the SLURM run's results against the local run's")
    rep.check(
        (slurm_dir / METRICS).read_bytes() == (local_dir / METRICS).read_bytes(),
        f"{METRICS} byte-identical",
    )
    h5_local = sorted(p.relative_to(local_dir) for p in (local_dir / "results").rglob("*.h5"))
    h5_slurm = sorted(p.relative_to(slurm_dir) for p in (slurm_dir / "results").rglob("*.h5"))
    rep.check(h5_local == h5_slurm and len(h5_local) > 0, f"the same {len(h5_local)} HDF5 artefacts")
    arrays, diffs = 0, []
    for rel in h5_local:
        if (slurm_dir / rel).exists():
            n, d = compare_h5(local_dir / rel, slurm_dir / rel)
            arrays += n
            diffs += [f"{rel}: {x}" for x in d]
    rep.check(not diffs, f"all {arrays} arrays equal, and every attribute but creation times and timings{some(diffs)}")

    verdict = "PASSED" if not rep.failures else "FAILED: " + "; ".join(rep.failures)
    rep.line(
        f"cluster-test {verdict} ({time.monotonic() - t0:.0f} s: SLURM run 1 {first_s:.0f} s, rerun {rerun_s:.0f} s)"
    )
    return 0 if not rep.failures else 1


if __name__ == "__main__":
    sys.exit(main())
