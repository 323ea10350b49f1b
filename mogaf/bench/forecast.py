"""`python -m mogaf.bench forecast`: future 3D EPE and training time of every
forecaster on procedural trajectory sets.

Each set is a ground-truth array (G, T_total, 7). For every observation ratio
the first round(ratio * T_total) frames are observed, the rest forecast. EPE is
the mean over Gaussians and forecast steps of ||mu_hat - mu||; the rotation
error is the mean geodesic angle (degrees); train time is wall-clock per group.
A --json row also keeps the EPE at each forecast step (epe_per_step), to tell
a first-step bias from a drift.

Trajectory sources are pluggable:
  * built-in procedural sets (--sets, mogaf.forecast.synthetic.TRAJECTORY_SETS);
  * --npz FILE: every array in the file (shape (G, T_total, 7)) is one set;
  * --source MODULE:FUNCTION: a callable returning one such array or a
    mapping name -> array;
  * from Python: evaluate_trajectories(array, ...) / run_benchmark({name: array}).

Budgets: the baselines at their upstream settings (--budget paper) take about
an hour (GCN: 2001 epochs of a 6-block GCN over 100 control points) and 5-33 min
(ODE: 40 epochs of a 4-layer d=128 transformer encoder over every (window,
Gaussian) pair of a 256-Gaussian set, 36-72 observed frames) per group on one
loaded CPU core (--device auto runs them on a GPU where torch sees one); --json with
--resume keeps finished rows across runs of the same code (the file records a
digest of mogaf's sources: rows of older code kept beside new ones would
compare two programs). The default --budget cpu shortens only their
epochs (REDUCED in _forecast_report.py) and marks them with '*' in the table; MoGaF always runs
at its defaults.

--from-json A.json B.json ... runs nothing and prints one Markdown comparison
table (a line per set and ratio, a column per method) from such files, e.g.
MoGaF and the references at defaults from one run and each baseline at its
paper budget from another; --only keeps the rows of the sets it names.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mogaf.artefact import atomic_path
from mogaf.devices import resolve_device
from mogaf.errors import MogafError
from mogaf.forecast import quat
from mogaf.forecast.params import METHODS
from mogaf.forecast.registry import fit_and_rollout
from mogaf.forecast.synthetic import TRAJECTORY_SETS
from mogaf.paths import check_writable

from ._forecast_report import (  # noqa: F401  (read_rows, summary_table, per_step_table, column_name re-exported)
    REDUCED,
    TORCH_METHODS,
    column_name,
    comparison_table,
    format_table,
    markdown_report,
    per_step_table,
    read_rows,
    set_selected,
    summary_table,
)
from ._forecast_sources import (  # noqa: F401  (the synthetic_* --source functions re-exported)
    _load_source,
    code_digest,
    synthetic_articulated,
    synthetic_bounce,
    synthetic_default,
    synthetic_hard,
    synthetic_scene_sets,
)


def split(traj: np.ndarray, ratio: float) -> tuple[np.ndarray, np.ndarray]:
    traj = np.asarray(traj, dtype=np.float64)
    if traj.ndim != 3 or traj.shape[2] != 7:
        raise MogafError(f"bench forecast: trajectories must have shape (G, T_total, 7), got {traj.shape}")
    t_obs = int(round(ratio * traj.shape[1]))
    if not 2 <= t_obs < traj.shape[1]:
        raise MogafError(f"bench forecast: ratio {ratio} leaves {t_obs} of {traj.shape[1]} frames observed")
    return traj[:, :t_obs], traj[:, t_obs:]


def errors(poses: np.ndarray, future: np.ndarray) -> tuple[float, float]:
    """(mean 3D EPE, mean rotation error in degrees)."""
    epe = float(epe_per_step(poses, future).mean())
    rot = float(np.degrees(quat.angle_between(poses[..., 3:], future[..., 3:])).mean())
    return epe, rot


def epe_per_step(poses: np.ndarray, future: np.ndarray) -> np.ndarray:
    """(T_fc,) 3D EPE at each forecast step, averaged over Gaussians: where a
    rollout goes wrong (a first-step bias or a slow drift)."""
    return np.linalg.norm(poses[..., :3] - future[..., :3], axis=-1).mean(axis=0)


def evaluate_trajectories(
    traj: np.ndarray,
    ratio: float,
    methods: Sequence[str] = METHODS,
    params: Mapping[str, Mapping[str, Any]] | None = None,
    seed: int = 0,
    progress: Callable[[dict[str, Any]], None] | None = None,
    device: str = "cpu",
) -> list[dict[str, Any]]:
    """Fit every method on the observed part of `traj` (G, T_total, 7) and
    score its forecast of the rest. One row per method, each passed to
    `progress` as soon as it is scored. `device`: where the torch-based methods compute."""
    obs, fut = split(traj, ratio)
    rows = []
    for method in methods:
        p = dict((params or {}).get(method, {}))
        t0 = time.perf_counter()
        res = fit_and_rollout(method, obs, fut.shape[1], p, seed=seed, device=device)
        wall = time.perf_counter() - t0
        epe, rot = errors(res.poses, fut)
        flags = [k for k in ("ode_step_cap_hit", "window_clipped") if res.info.get(k)]
        rows.append(
            {
                "method": method,
                "ratio": ratio,
                "gaussians": int(traj.shape[0]),
                "observed_frames": int(obs.shape[1]),
                "forecast_frames": int(fut.shape[1]),
                "epe": epe,
                "rot_err_deg": rot,
                "epe_per_step": [round(float(v), 6) for v in epe_per_step(res.poses, fut)],
                "train_s": float(res.info.get("train_time_s", 0.0)),
                "total_s": wall,
                "final_loss": res.info.get("final_loss"),
                "flags": flags,
            }
        )
        if progress:
            progress(rows[-1])
    return rows


def run_benchmark(
    sources: Mapping[str, np.ndarray | Callable[[], np.ndarray]],
    ratios: Sequence[float] = (0.6, 0.8),
    methods: Sequence[str] = METHODS,
    params: Mapping[str, Mapping[str, Any]] | None = None,
    seed: int = 0,
    progress: Callable[[dict[str, Any]], None] | None = None,
    done: Sequence[Mapping[str, Any]] = (),
    device: str = "cpu",
) -> list[dict[str, Any]]:
    """Rows of every (set, ratio, method); rows in `done` (same set, ratio and
    method) are kept as they are and not recomputed."""
    finished = {(r["set"], float(r["ratio"]), r["method"]): dict(r) for r in done}
    rows: list[dict[str, Any]] = []
    for name, src in sources.items():
        traj = src() if callable(src) else src
        for ratio in ratios:
            t_obs = split(traj, ratio)[0].shape[1]
            todo = []
            for m in methods:
                row = finished.get((name, float(ratio), m))
                if row is None:
                    todo.append(m)
                elif (row.get("gaussians"), row.get("observed_frames")) != (traj.shape[0], t_obs):
                    # a kept row must have been scored on these same trajectories
                    raise MogafError(
                        f"bench forecast: the kept row {name} ratio {ratio} {m} was scored on "
                        f"{row.get('gaussians')} Gaussians x {row.get('observed_frames')} observed frames, this set has "
                        f"{traj.shape[0]} x {t_obs}; remove the --json file or drop --resume"
                    )
            fresh: dict[str, dict[str, Any]] = {}
            if todo:

                def report(row: dict[str, Any], name: str = name, fresh: dict = fresh) -> None:
                    row = {"set": name, **row}
                    fresh[row["method"]] = row
                    if progress:
                        progress(row)

                evaluate_trajectories(traj, ratio, todo, params, seed, report, device)
            rows.extend(fresh.get(m) or finished[(name, float(ratio), m)] for m in methods)
    return rows


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m mogaf.bench forecast", description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--sets", default=",".join(TRAJECTORY_SETS), help="built-in procedural sets (comma list, or 'none')"
    )
    ap.add_argument("--npz", action="append", default=[], help="file of (G, T_total, 7) arrays, one set each")
    ap.add_argument("--source", action="append", default=[], help="MODULE:FUNCTION returning an array or {name: array}")
    ap.add_argument("--gaussians", type=int, default=2000, help="Gaussians per procedural set")
    ap.add_argument("--frames", type=int, default=60, help="frames per procedural sequence")
    ap.add_argument("--ratios", default="0.6,0.8")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--budget", choices=("cpu", "paper"), default="cpu")
    ap.add_argument("--params", default="{}", help="JSON {method: {param: value}} overrides")
    ap.add_argument(
        "--threads", type=int, default=1, help="torch intra-op threads for every method (0 = torch default)"
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--device",
        choices=("cpu", "auto", "cuda"),
        default="cpu",
        help="where the torch-based methods compute (auto: CUDA where torch sees it); the device used is recorded in --json",
    )
    ap.add_argument(
        "--only",
        default="",
        help="comma-separated glob patterns: keep only the sets whose name matches one (with --from-json: their rows)",
    )
    ap.add_argument("--json", help="also write the rows here (rewritten after every row)")
    ap.add_argument(
        "--resume",
        action="store_true",
        help="keep the rows already in --json (same budget, parameters, seed, device and code) and compute only the missing ones",
    )
    ap.add_argument(
        "--from-json",
        action="append",
        default=[],
        metavar="FILE",
        help="run nothing: print one Markdown table (set x ratio, a column per method) from these --json files",
    )
    ap.add_argument(
        "--summary",
        action="store_true",
        help="with --from-json: also the mean EPE and win counts per method, and the EPE at the first, middle and last step",
    )
    return ap


def _comma_list(text: str) -> list[str]:
    """The non-empty, stripped items of a comma-separated option."""
    return [x.strip() for x in text.split(",") if x.strip()]


def _parse_methods(text: str) -> list[str]:
    methods = _comma_list(text)
    bad = [m for m in methods if m not in METHODS]
    if bad:
        raise MogafError(f"bench forecast: unknown method(s) {', '.join(bad)} (choose from {', '.join(METHODS)})")
    return methods


def _parse_overrides(text: str) -> Any:
    try:
        overrides = json.loads(text)
    except json.JSONDecodeError as exc:
        raise MogafError(f"bench forecast: --params is not JSON ({exc})") from None
    if not isinstance(overrides, dict) or not all(isinstance(v, dict) for v in overrides.values()):
        raise MogafError(f"bench forecast: --params must be a JSON object {{method: {{param: value}}}}, got {text!r}")
    return overrides


def _parse_ratios(text: str) -> list[float]:
    """--ratios: observed fractions, each in (0, 1)."""
    try:
        ratios = [float(r) for r in _comma_list(text)]
    except ValueError:
        ratios = []
    if not ratios or not all(0 < r < 1 for r in ratios):
        raise MogafError(f"bench forecast: --ratios takes numbers in (0, 1) separated by commas, got {text!r}")
    return ratios


def _method_params(
    methods: Sequence[str], budget: str, threads: int, overrides: Mapping[str, Any]
) -> tuple[dict[str, dict[str, Any]], dict[str, dict[str, Any]]]:
    """(each method's parameters, the reduced-budget ones of those run on --budget cpu, without num_threads)."""
    params: dict[str, dict[str, Any]] = {}
    reduced: dict[str, dict[str, Any]] = {}
    for m in methods:
        p: dict[str, Any] = {}
        shortened = budget == "cpu" and m in REDUCED
        if shortened:
            p.update(REDUCED[m])
        if m in TORCH_METHODS:
            p["num_threads"] = threads
        p.update(overrides.get(m, {}))
        params[m] = p
        if shortened:
            reduced[m] = {k: v for k, v in p.items() if k != "num_threads"}
    return params, reduced


def _builtin_sources(sets: str, gaussians: int, frames: int) -> dict[str, Any]:
    """--sets: the named procedural sets, each made when it is run."""
    sources: dict[str, Any] = {}
    if sets == "none":
        return sources
    for name in _comma_list(sets):
        if name not in TRAJECTORY_SETS:
            raise MogafError(f"bench forecast: unknown set '{name}' (choose from {', '.join(TRAJECTORY_SETS)})")
        fn = TRAJECTORY_SETS[name]
        sources[name] = lambda fn=fn: fn(gaussians, frames)
    return sources


def _npz_sources(paths: Sequence[str]) -> dict[str, Any]:
    """--npz: every array of every file, one set each."""
    sources: dict[str, Any] = {}
    for path in paths:
        try:
            with np.load(path) as data:
                for key in data.files:
                    sources[f"{key}"] = np.array(data[key])
        except (OSError, ValueError) as exc:  # ValueError: not an .npz (or a pickled array)
            raise MogafError(f"{path}: cannot read as .npz ({exc})") from None
    return sources


def _select_sources(args: argparse.Namespace, patterns: Sequence[str]) -> dict[str, Any]:
    """The trajectory sets of --sets, --npz and --source, those --only keeps."""
    sources = _builtin_sources(args.sets, args.gaussians, args.frames)
    sources.update(_npz_sources(args.npz))
    for spec in args.source:
        sources.update(_load_source(spec))
    if patterns:
        sources = {k: v for k, v in sources.items() if set_selected(k, patterns)}
    if not sources:
        raise MogafError("bench forecast: no trajectory sets selected")
    return sources


def _done_rows(args: argparse.Namespace, header: dict[str, Any]) -> list[dict[str, Any]]:
    """The rows --resume keeps (may widen header["params"] by the file's other methods)."""
    if args.resume:
        if not args.json:
            raise MogafError("bench forecast: --resume needs --json (the file the rows are kept in)")
        return _resumable_rows(Path(args.json), header)
    if args.json and Path(args.json).exists():
        # rows of a paper-budget run cost hours: never overwrite them by accident
        raise MogafError(f"{args.json}: exists; pass --resume to go on with it, or remove it")
    return []


def _progress_writer(
    json_path: str | None, header: Mapping[str, Any], kept: list[dict[str, Any]]
) -> Callable[[dict[str, Any]], None]:
    """Reports each scored row on stderr; with --json also keeps it and rewrites the file."""

    def progress(row: dict[str, Any]) -> None:
        if json_path:
            kept.append(row)
            _write_json(Path(json_path), {**header, "rows": kept})
        print(
            f"  {row['set']} ratio={row['ratio']:.2f} {row['method']}: EPE {row['epe']:.4f} "
            f"rot {row['rot_err_deg']:.2f} deg, train {row['train_s']:.1f} s",
            file=sys.stderr,
            flush=True,
        )

    return progress


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(list(argv) if argv is not None else None)

    try:
        patterns = _comma_list(args.only)
        if args.from_json:
            report = markdown_report if args.summary else comparison_table
            print(report(args.from_json, patterns))
            return 0
        methods = _parse_methods(args.methods)
        ratios = _parse_ratios(args.ratios)
        params, reduced = _method_params(methods, args.budget, args.threads, _parse_overrides(args.params))
        sources = _select_sources(args, patterns)
        # the device the rows are computed on ("auto" resolved: a CPU-only machine's rows are CPU rows)
        device = resolve_device(args.device, "bench forecast").type
        header = {"budget": args.budget, "params": params, "seed": args.seed, "device": device, "code": code_digest()}
        done = _done_rows(args, header)
        if args.json:
            check_writable(args.json)  # not after the first row's minutes of training

        print(
            f"forecast benchmark: budget={args.budget}, threads={args.threads}, seed={args.seed}, device={device}",
            flush=True,
        )

        kept = list(done)
        progress = _progress_writer(args.json, header, kept)
        rows = run_benchmark(sources, ratios, methods, params, args.seed, progress, done, device)
    except MogafError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(format_table(rows, reduced))
    if args.json:  # every row so far, also kept rows of sets or methods not run this time
        _write_json(Path(args.json), {**header, "rows": kept})
    return 0


def _write_json(path: Path, obj: Mapping[str, Any]) -> None:
    """Whole file or nothing: a run stopped mid-write leaves the previous rows.
    (Not mogaf.artefact.write_json: a row may hold a NaN final loss.)"""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=1) + "\n")


def _resumable_rows(path: Path, header: dict[str, Any]) -> list[dict[str, Any]]:
    """The file's rows, after checking they were made with these settings; widens
    header["params"] by the file's other methods so a rewrite keeps them."""
    if not path.exists():
        return []
    try:
        old = json.loads(path.read_text())
        rows = list(old["rows"])
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise MogafError(f"{path}: not a forecast benchmark file ({exc})") from None
    want = json.loads(json.dumps(header))  # as JSON would give it back
    for key in ("budget", "seed"):
        if key not in old:
            raise MogafError(f"{path}: has no '{key}' (written before --resume existed); remove it or drop --resume")
        if old.get(key) != want[key]:
            raise MogafError(f"{path}: written with another {key} ({old.get(key)!r}); remove it or drop --resume")
    # files from before --device ran on the CPU
    if old.get("device", "cpu") != want["device"]:
        raise MogafError(
            f"{path}: written with another device ({old.get('device', 'cpu')!r}); remove it or drop --resume"
        )
    if old.get("code") != want["code"]:
        made = f"code {old['code']!r}" if "code" in old else "code from before digests were recorded"
        raise MogafError(
            f"{path}: its rows were computed by other mogaf code ({made}; this is {want['code']}); "
            "remove it or drop --resume"
        )
    old_params = old.get("params") or {}
    for method, p in want["params"].items():
        if method in old_params and old_params[method] != p:
            raise MogafError(
                f"{path}: written with other {method} parameters ({old_params[method]!r}); remove it or drop --resume"
            )
    # rows of methods no longer asked for stay in the file with their parameters
    header["params"] = {**old_params, **header["params"]}
    return rows


if __name__ == "__main__":
    sys.exit(main())
