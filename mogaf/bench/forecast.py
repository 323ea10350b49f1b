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
loaded CPU core; --json with
--resume keeps finished rows across runs. The default --budget cpu shortens only their
epochs (REDUCED below) and marks them with '*' in the table; MoGaF always runs
at its defaults.

--from-json A.json B.json ... runs nothing and prints one Markdown comparison
table (a line per set and ratio, a column per method) from such files, e.g.
MoGaF and the references at defaults from one run and each baseline at its
paper budget from another.
"""

from __future__ import annotations

import argparse
import fnmatch
import importlib
import json
import math
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from mogaf.artefact import atomic_path
from mogaf.errors import MogafError
from mogaf.forecast import METHODS, fit_and_rollout, quat
from mogaf.forecast.synthetic import TRAJECTORY_SETS
from mogaf.paths import cache_dir

# Shortened training of the baselines for a CPU run (--budget cpu).
REDUCED: dict[str, dict[str, Any]] = {
    "gcn": {"epochs": 60},  # of 2001
    "ode": {"epochs": 2, "max_gaussians_per_epoch": 1024},  # of 40 epochs over all Gaussians
}
TORCH_METHODS = ("mogaf", "mogaf_paper", "gcn", "ode")


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
) -> list[dict[str, Any]]:
    """Fit every method on the observed part of `traj` (G, T_total, 7) and
    score its forecast of the rest. One row per method, each passed to
    `progress` as soon as it is scored."""
    obs, fut = split(traj, ratio)
    rows = []
    for method in methods:
        p = dict((params or {}).get(method, {}))
        t0 = time.perf_counter()
        res = fit_and_rollout(method, obs, fut.shape[1], p, seed=seed)
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

                evaluate_trajectories(traj, ratio, todo, params, seed, report)
            rows.extend(fresh.get(m) or finished[(name, float(ratio), m)] for m in methods)
    return rows


def format_table(rows: Sequence[Mapping[str, Any]], reduced: Mapping[str, Mapping[str, Any]] | None = None) -> str:
    """A text table; `reduced` maps shortened methods to the settings used."""
    reduced = reduced or {}
    head = f"{'set':<18} {'ratio':>5} {'method':<19} {'EPE':>9} {'rot(deg)':>9} {'train s':>8}  flags"
    lines = [head, "-" * len(head)]
    for r in rows:
        name = r["method"] + ("*" if r["method"] in reduced else "")
        lines.append(
            f"{r['set']:<18} {r['ratio']:>5.2f} {name:<19} {r['epe']:>9.4f} {r['rot_err_deg']:>9.2f} "
            f"{r['train_s']:>8.1f}  {','.join(r['flags'])}"
        )
    if reduced:
        lines.append("* shortened training (--budget cpu): " + "; ".join(f"{m}: {p}" for m, p in reduced.items()))
    return "\n".join(lines)


def read_rows(path: Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """(header, rows) of a --json file written by this benchmark."""
    try:
        doc = json.loads(Path(path).read_text())
        rows = [dict(r) for r in doc["rows"]]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise MogafError(f"{path}: not a forecast benchmark file ({exc})") from None
    for i, r in enumerate(rows):
        missing = [k for k in ("set", "ratio", "method", "epe", "train_s") if k not in r]
        if missing:
            raise MogafError(f"{path}: row {i} has no {', '.join(missing)}")
    return {k: v for k, v in doc.items() if k != "rows"}, rows


def _same_number(a: float, b: float) -> bool:
    return a == b or (math.isnan(a) and math.isnan(b))


def comparison_table(paths: Sequence[str | Path]) -> str:
    """One Markdown table from several --json files: a line per (set, ratio),
    a future-EPE column per method (lowest in bold) and the training time of
    the learned methods. A baseline from a --budget cpu file is its own column,
    marked '*'. The same row in two files must agree."""
    cells: dict[tuple[str, float], dict[str, dict[str, Any]]] = {}
    origin: dict[tuple[str, float, str], str] = {}
    shapes: dict[tuple[str, float], tuple[Any, Any]] = {}
    columns: set[str] = set()
    for path in paths:
        header, rows = read_rows(Path(path))
        if header.get("budget") not in ("cpu", "paper"):
            raise MogafError(f"{path}: has no budget 'cpu' or 'paper' (written before budgets were recorded?)")
        for r in rows:
            key, method = (str(r["set"]), float(r["ratio"])), str(r["method"])
            col = method + ("*" if header.get("budget") == "cpu" and method in REDUCED else "")
            shape = (r.get("gaussians"), r.get("observed_frames"))
            if shapes.setdefault(key, shape) != shape:
                raise MogafError(
                    f"{path}: {key[0]} ratio {key[1]} was scored on other trajectories than in an earlier file"
                )
            old = cells.setdefault(key, {}).get(col)
            if old is not None and not _same_number(old["epe"], r["epe"]):
                raise MogafError(
                    f"{path}: {key[0]} ratio {key[1]} {col} has EPE {r['epe']:.6g}, "
                    f"{origin[(*key, col)]} has {old['epe']:.6g}"
                )
            cells[key][col] = r
            origin[(*key, col)] = str(path)
            columns.add(col)
    if not cells:
        raise MogafError("bench forecast: the --from-json files hold no rows")
    known = [c for m in METHODS for c in (m, m + "*")]
    order = [c for c in known if c in columns] + sorted(columns - set(known))  # methods of other versions last
    timed = [c for c in order if c.rstrip("*") in TORCH_METHODS]
    head = ["set", "ratio"] + [f"{c} EPE" for c in order] + [f"{c} train s" for c in timed]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for (name, ratio), row in cells.items():
        finite = [r["epe"] for r in row.values() if math.isfinite(r["epe"])]
        best = min(finite) if finite else None
        out = [name, f"{ratio:.2f}"]
        for c in order:
            r = row.get(c)
            if r is None:
                out.append("–")
                continue
            text = f"{r['epe']:.4f}" + (f" ({', '.join(r['flags'])})" if r.get("flags") else "")
            out.append(f"**{text}**" if r["epe"] == best else text)
        out += [f"{row[c]['train_s']:,.0f}" if c in row else "–" for c in timed]
        lines.append("| " + " | ".join(out) + " |")
    if any(c.endswith("*") for c in order):
        lines.append("")
        lines.append("\\* shortened training (--budget cpu): " + "; ".join(f"{m}: {REDUCED[m]}" for m in REDUCED))
    return "\n".join(lines)


def _cells(paths: Sequence[str | Path]) -> dict[tuple[str, float], dict[str, dict[str, Any]]]:
    """(set, ratio) -> column -> row, columns named as in comparison_table
    (a --budget cpu baseline is 'method*'); the files are checked there."""
    cells: dict[tuple[str, float], dict[str, dict[str, Any]]] = {}
    for path in paths:
        header, rows = read_rows(Path(path))
        for r in rows:
            col = str(r["method"]) + ("*" if header.get("budget") == "cpu" and r["method"] in REDUCED else "")
            cells.setdefault((str(r["set"]), float(r["ratio"])), {})[col] = r
    return cells


def summary_table(paths: Sequence[str | Path], against: Sequence[str] = ("constant_velocity", "frozen")) -> str:
    """Per method: the mean future EPE over the rows every method in the table
    has, and on how many of its rows it beats each reference in `against`."""
    comparison_table(paths)  # the same checks (agreeing files)
    cells = _cells(paths)
    columns = sorted(
        {c for row in cells.values() for c in row},
        key=lambda c: (METHODS.index(c.rstrip("*")) if c.rstrip("*") in METHODS else 99, c),
    )
    shared = [k for k, row in cells.items() if all(c in row for c in columns)]
    head = ["method", f"mean EPE ({len(shared)} rows with every method)"] + [f"beats {a}" for a in against]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    means = {c: float(np.mean([cells[k][c]["epe"] for k in shared])) if shared else math.nan for c in columns}
    best = min((v for v in means.values() if math.isfinite(v)), default=None)
    for c in columns:
        out = [
            c,
            (f"**{means[c]:.4f}**" if means[c] == best else f"{means[c]:.4f}") if math.isfinite(means[c]) else "–",
        ]
        for a in against:
            both = [k for k, row in cells.items() if c in row and a in row]
            if c == a or not both:
                out.append("–")
                continue
            wins = sum(cells[k][c]["epe"] < cells[k][a]["epe"] for k in both)
            out.append(f"{wins} of {len(both)} ({100.0 * wins / len(both):.0f} %)")
        lines.append("| " + " | ".join(out) + " |")
    return "\n".join(lines)


def per_step_table(paths: Sequence[str | Path], fractions: Sequence[float] = (0.0, 0.5, 1.0)) -> str:
    """Future EPE at the first, middle and last forecast step of every row and
    method that kept its per-step EPE: where a rollout goes wrong."""
    cells = _cells(paths)
    columns = sorted(
        {c for row in cells.values() for c, r in row.items() if r.get("epe_per_step")},
        key=lambda c: (METHODS.index(c.rstrip("*")) if c.rstrip("*") in METHODS else 99, c),
    )
    head = ["set", "ratio", "steps"] + [f"{c} EPE at steps" for c in columns]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for (name, ratio), row in cells.items():
        n = max((len(r.get("epe_per_step") or []) for r in row.values()), default=0)
        if not n:
            continue
        picks = sorted({min(n - 1, int(round(f * (n - 1)))) for f in fractions})
        out = [name, f"{ratio:.2f}", " / ".join(str(i + 1) for i in picks)]
        for c in columns:
            steps = (row.get(c) or {}).get("epe_per_step") or []
            out.append(" / ".join(f"{steps[i]:.4f}" for i in picks) if len(steps) == n else "–")
        lines.append("| " + " | ".join(out) + " |")
    return "\n".join(lines)


def markdown_report(paths: Sequence[str | Path]) -> str:
    """What --from-json --summary prints: the comparison table, the summary
    (mean EPE, win counts) and the per-step EPE (docs/forecasting.md keeps it)."""
    return "\n\n".join([comparison_table(paths), summary_table(paths), per_step_table(paths)])


def _local_rotations(points: np.ndarray, k: int = 8) -> np.ndarray:
    """(P, T, 4) wxyz rotation of each point's k-neighbourhood (nearest at
    frame 0) from frame 0 to every frame: the best rigid fit, det = +1."""
    from scipy.spatial import cKDTree

    from mogaf.rigid import procrustes_numpy  # local: mogaf.rigid imports torch, which only this path needs

    k = min(k + 1, points.shape[0])
    _, nn = cKDTree(points[:, 0]).query(points[:, 0], k=k)
    src = points[nn, 0][:, None]  # (P, 1, k, 3)
    dst = points[nn].transpose(0, 2, 1, 3)  # (P, T, k, 3)
    R, _ = procrustes_numpy(src, dst)
    return quat.make_continuous(_matrix_to_quat(R), axis=1)


def _matrix_to_quat(R: np.ndarray) -> np.ndarray:
    import torch

    from mogaf.representation import (
        matrix_to_quat,  # local: mogaf.representation imports torch, which only this path needs
    )

    return matrix_to_quat(torch.from_numpy(np.ascontiguousarray(R, dtype=np.float64))).numpy()


def synthetic_scene_sets(preset: str = "default") -> dict[str, np.ndarray]:
    """Ground-truth trajectories of the embedded synthetic scene, one set per
    object (the group-wise setting): (P_obj, T, 7) [surface point, rotation].
    Rotations: the object pose for rigid objects, the local best rigid fit of
    the point's neighbourhood for non-rigid ones. The scene is generated into
    the cache once."""
    import json as _json

    from mogaf.synth import generate_scene  # local: mogaf.synth imports cv2, which only this path needs

    root = cache_dir("bench_forecast", f"synthetic_{preset}")
    if not (root / "mogaf_gt" / "points3d.npy").exists():
        generate_scene(root, {"preset": preset})
    gt = root / "mogaf_gt"
    points = np.load(gt / "points3d.npy").astype(np.float64)
    inst = np.load(gt / "points_instance.npy")
    poses = np.load(gt / "object_poses.npy")
    objects = _json.loads((gt / "instances.json").read_text())["instances"]
    out = {}
    for obj in objects:
        oid = int(obj["id"])
        if oid == 0:
            continue
        sel = np.flatnonzero(inst == oid)
        if sel.size < 2:
            continue
        if int(obj.get("pose_index", -1)) >= 0:
            R = poses[int(obj["pose_index"])][:, :3, :3]  # (T, 3, 3)
            q = quat.make_continuous(np.repeat(_matrix_to_quat(R)[None], sel.size, axis=0), axis=1)
        else:
            q = _local_rotations(points[sel])
        out[f"{preset}/{obj['name']}"] = np.concatenate([points[sel], q], axis=-1)
    return out


def synthetic_default() -> dict[str, np.ndarray]:
    return synthetic_scene_sets("default")


def synthetic_hard() -> dict[str, np.ndarray]:
    return synthetic_scene_sets("hard")


def synthetic_articulated() -> dict[str, np.ndarray]:
    return synthetic_scene_sets("articulated")


def synthetic_bounce() -> dict[str, np.ndarray]:
    return synthetic_scene_sets("bounce")


def _load_source(spec: str) -> dict[str, Any]:
    mod_name, _, func_name = spec.partition(":")
    if not func_name:
        raise MogafError(f"bench forecast: --source must be MODULE:FUNCTION, got '{spec}'")
    try:
        obj = getattr(importlib.import_module(mod_name), func_name)()
    except (ImportError, AttributeError) as exc:
        raise MogafError(f"bench forecast: cannot load --source {spec} ({exc})") from None
    if isinstance(obj, Mapping):
        return dict(obj)
    return {func_name: obj}


def main(argv: Sequence[str] | None = None) -> int:
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
        "--only", default="", help="comma-separated glob patterns: keep only the sets whose name matches one"
    )
    ap.add_argument("--json", help="also write the rows here (rewritten after every row)")
    ap.add_argument(
        "--resume",
        action="store_true",
        help="keep the rows already in --json (same budget, parameters and seed) and compute only the missing ones",
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
    args = ap.parse_args(list(argv) if argv is not None else None)

    try:
        if args.from_json:
            print(markdown_report(args.from_json) if args.summary else comparison_table(args.from_json))
            return 0
        methods = [m.strip() for m in args.methods.split(",") if m.strip()]
        bad = [m for m in methods if m not in METHODS]
        if bad:
            raise MogafError(f"bench forecast: unknown method(s) {', '.join(bad)} (choose from {', '.join(METHODS)})")
        ratios = [float(r) for r in args.ratios.split(",")]
        try:
            overrides = json.loads(args.params)
        except json.JSONDecodeError as exc:
            raise MogafError(f"bench forecast: --params is not JSON ({exc})") from None
        params: dict[str, dict[str, Any]] = {}
        reduced: dict[str, dict[str, Any]] = {}
        for m in methods:
            p: dict[str, Any] = {}
            if args.budget == "cpu" and m in REDUCED:
                p.update(REDUCED[m])
                reduced[m] = {}
            if m in TORCH_METHODS:
                p["num_threads"] = args.threads
            p.update(overrides.get(m, {}))
            params[m] = p
            if m in reduced:
                reduced[m] = {k: v for k, v in p.items() if k != "num_threads"}

        sources: dict[str, Any] = {}
        if args.sets != "none":
            for name in [s.strip() for s in args.sets.split(",") if s.strip()]:
                if name not in TRAJECTORY_SETS:
                    raise MogafError(f"bench forecast: unknown set '{name}' (choose from {', '.join(TRAJECTORY_SETS)})")
                fn = TRAJECTORY_SETS[name]
                sources[name] = lambda fn=fn: fn(args.gaussians, args.frames)
        for path in args.npz:
            try:
                with np.load(path) as data:
                    for key in data.files:
                        sources[f"{key}"] = np.array(data[key])
            except OSError as exc:
                raise MogafError(f"{path}: cannot read ({exc})") from None
        for spec in args.source:
            sources.update(_load_source(spec))
        if args.only:
            patterns = [x.strip() for x in args.only.split(",") if x.strip()]
            sources = {k: v for k, v in sources.items() if any(fnmatch.fnmatchcase(k, pat) for pat in patterns)}
        if not sources:
            raise MogafError("bench forecast: no trajectory sets selected")
        header = {"budget": args.budget, "params": params, "seed": args.seed}
        done: list[dict[str, Any]] = []
        if args.resume:  # may widen header["params"] by the file's other methods
            if not args.json:
                raise MogafError("bench forecast: --resume needs --json (the file the rows are kept in)")
            done = _resumable_rows(Path(args.json), header)
        elif args.json and Path(args.json).exists():
            # rows of a paper-budget run cost hours: never overwrite them by accident
            raise MogafError(f"{args.json}: exists; pass --resume to go on with it, or remove it")

        print(f"forecast benchmark: budget={args.budget}, threads={args.threads}, seed={args.seed}", flush=True)

        kept = list(done)

        def progress(row: dict[str, Any]) -> None:
            if args.json:
                kept.append(row)
                _write_json(Path(args.json), {**header, "rows": kept})
            print(
                f"  {row['set']} ratio={row['ratio']:.2f} {row['method']}: EPE {row['epe']:.4f} "
                f"rot {row['rot_err_deg']:.2f} deg, train {row['train_s']:.1f} s",
                file=sys.stderr,
                flush=True,
            )

        rows = run_benchmark(sources, ratios, methods, params, args.seed, progress, done)
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
