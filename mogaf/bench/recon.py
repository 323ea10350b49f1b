"""Benchmark of the reconstruction stage: `python -m mogaf.bench recon`.

Cases (each builds its inputs with the library: generator / reader ->
scene.h5 -> split.h5 -> priors.h5, cached in --workdir):

- synthetic: the default synthetic scene (mogaf.synth, DyCheck iPhone
  layout, 160x120, 60 frames), ratio 0.6, default recon parameters;
- mujoco/scene3_collision, mujoco/scene7_deformation: the shared MuJoCo
  scenes (D-NeRF layout, 800x800 read with downscale 4 -> 200x200),
  ratio 0.8 (skipped when ../shared/data is absent).

Columns: wall time of run_recon_stage (init + training + export; the CPU
load average at the start and end is printed too, the machine may be
shared), train PSNR (all observed frames, at training resolution), held-out
PSNR (the split's evaluation_observed frames: held-out cameras / test
frames at observed times), held-out mPSNR (DyCheck co-visibility mask, where
the scene has one), and for the synthetic scene the 3D trajectory error:
for every ground-truth surface point, the nearest fg Gaussian (opacity >
0.1) at the canonical time step; the mean distance between the two
trajectories over the observed steps, in metres and in % of the scene extent
(diagonal of the bounding box of the ground-truth points over those steps),
and the error of those trajectories' per-step displacement (their velocity)
over the middle half of the observed steps and at the last one: forecasts
extrapolate from the last step, which a reconstruction constrains from one
side only.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from mogaf.artefact import atomic_path, config_digest
from mogaf.datasets import read_scene
from mogaf.errors import MogafError
from mogaf.metrics.image import mpsnr, psnr
from mogaf.paths import cache_dir, check_writable
from mogaf.priors.stage import run_priors_stage
from mogaf.recon.stage import run_recon_stage
from mogaf.rendering import render_model
from mogaf.representation import load_model
from mogaf.scene import save_scene
from mogaf.split import load_frames, load_ground_truth, read_split, split_scene, write_split
from mogaf.synth.generate import generate_scene

SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data"
MUJOCO = ("scene3_collision", "scene7_deformation")


def _prepare_synthetic(work: Path, preset: str = "default") -> tuple[Path, Path, Path]:
    root = work / f"synthetic_{preset}"
    src = root / "source"
    if not (src / "dataset.json").exists():
        generate_scene(src, {"preset": preset})
    return _finish_inputs(
        root, lambda: read_scene("synthetic", src, dataset="synthetic", scene=preset, options={"scale": 1}), 0.6
    )


def _prepare_mujoco(work: Path, scene: str) -> tuple[Path, Path, Path] | None:
    folder = SHARED / "mujoco" / scene
    if not folder.is_dir():
        return None
    opts = {"downscale": 4, "background": [1.0, 1.0, 1.0]}
    return _finish_inputs(
        work / f"mujoco_{scene}", lambda: read_scene("dnerf", folder, dataset="mujoco", scene=scene, options=opts), 0.8
    )


def _finish_inputs(root: Path, reader, ratio: float) -> tuple[Path, Path, Path]:
    root.mkdir(parents=True, exist_ok=True)
    scene_h5, split_h5, priors_h5 = root / "scene.h5", root / f"split{ratio}.h5", root / f"priors{ratio}.h5"
    if not scene_h5.exists():
        save_scene(scene_h5, reader(), config_digest=config_digest({"bench": str(root.name)}))
    if not split_h5.exists():
        write_split(split_h5, split_scene(scene_h5, ratio))
    if not priors_h5.exists():
        run_priors_stage(scene_h5, split_h5, priors_h5, {})
    return scene_h5, split_h5, priors_h5


def heldout_psnr(scene_h5: Path, split_h5: Path, recon_h5: Path) -> tuple[float, float | None, float | None]:
    """Held-out PSNR, mPSNR (co-visible pixels) and the % of held-out pixels
    the training camera never sees (None without a co-visibility mask)."""
    model = load_model(recon_h5)
    frames = load_frames(scene_h5, read_split(split_h5), "evaluation_observed")
    ps, mps, unseen = [], [], []
    for i in range(frames.num_frames):
        out = render_model(model, int(frames.time_index[i]), frames.K[i], frames.w2c[i], frames.width, frames.height)
        img = out.features.numpy().clip(0, 1).astype(np.float64)
        gt = frames.images[i].astype(np.float64) / 255.0
        ps.append(psnr(img, gt))
        if frames.covisible is not None:
            unseen.append(100.0 * float(np.mean(frames.covisible[i] == 0)))
            if (frames.covisible[i] > 0).any():
                mps.append(mpsnr(img, gt, frames.covisible[i] > 0))
    return float(np.mean(ps)), (float(np.mean(mps)) if mps else None), (float(np.mean(unseen)) if unseen else None)


def matched_trajectories(scene_h5: Path, split_h5: Path, recon_h5: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """GT surface-point trajectories (P, T_obs, 3) and those of their nearest fg
    Gaussians (opacity > 0.1) at the canonical step; None without GT points."""
    from scipy.spatial import cKDTree

    split = read_split(split_h5)
    gt = load_ground_truth(scene_h5, split, "observed")
    if "points3d" not in gt:
        return None
    pts = np.asarray(gt["points3d"], dtype=np.float64)  # (P, T_obs, 3)
    model = load_model(recon_h5)
    steps = np.asarray(model.timesteps)
    k = int(np.flatnonzero(steps == int(model.attrs.get("canonical_timestep", steps[0])))[0])
    opac = 1.0 / (1.0 + np.exp(-np.asarray(model.fg.opacity_logits)))
    sel = np.flatnonzero(opac > 0.1)
    traj = np.asarray(model.trajectory_means, dtype=np.float64)[sel]  # (N, T, 3)
    _, nn = cKDTree(traj[:, k]).query(pts[:, k])
    return pts, traj[nn]


def trajectory_error(pts: np.ndarray, traj: np.ndarray) -> tuple[float, float]:
    """Mean 3D distance (scene units, % of extent) between GT surface-point
    trajectories `pts` and their matched Gaussians' `traj` (P, T_obs, 3)."""
    err = np.linalg.norm(traj - pts, axis=-1).mean()
    flat = pts.reshape(-1, 3)
    extent = float(np.linalg.norm(flat.max(0) - flat.min(0)))
    return float(err), float(100.0 * err / extent)


def velocity_error(pts: np.ndarray, traj: np.ndarray) -> tuple[float, float] | None:
    """Error of the matched Gaussians' per-step displacement (`traj`) against
    the GT points' (`pts`, both (P, T_obs, 3); scene units per step), averaged
    over the points: over the middle half of the observed steps, and at the
    last step, the one forecasts extrapolate from (a reconstruction constrains
    it from one side only). None with fewer than 4 observed steps."""
    if pts.shape[1] < 4:
        return None
    err = np.linalg.norm(np.diff(traj, axis=1) - np.diff(pts, axis=1), axis=-1).mean(axis=0)  # (T - 1,)
    interior = err[1:-1]  # without the steps at either end (at least one is left)
    n = interior.size
    return float(interior[n // 4 : n - n // 4].mean()), float(err[-1])


def run_case(
    name: str, inputs: tuple[Path, Path, Path], out_dir: Path, params: dict[str, Any], seed: int, progress: bool
) -> dict[str, Any]:
    scene_h5, split_h5, priors_h5 = inputs
    out = out_dir / f"{name.replace('/', '_')}_recon.h5"
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    run_recon_stage(scene_h5, split_h5, priors_h5, out, params, seed=seed, progress=progress)
    wall = time.perf_counter() - t0
    load1 = os.getloadavg()[0]
    return {**score_model(name, scene_h5, split_h5, out), "wall_s": wall, "load": (load0, load1)}


def score_model(name: str, scene_h5: Path, split_h5: Path, model_h5: Path) -> dict[str, Any]:
    """Every column but wall time and load, for a stored model (recon.h5 or refined.h5)."""
    model = load_model(model_h5)
    ho, mho, unseen = heldout_psnr(scene_h5, split_h5, model_h5)
    matched = matched_trajectories(scene_h5, split_h5, model_h5)  # None without GT points
    traj = None if matched is None else trajectory_error(*matched)
    vel = None if matched is None else velocity_error(*matched)
    return {
        "scene": name,
        "ratio": read_split(split_h5).ratio,
        "iterations": int(model.attrs.get("iterations", 0)),
        "gaussians": len(model.fg) + (0 if model.bg is None else len(model.bg)),
        "wall_s": None,
        "train_psnr": float(model.attrs.get("train_psnr", float("nan"))),
        "heldout_psnr": ho,
        "heldout_mpsnr": mho,
        "unseen_pct": unseen,
        "traj_err": None if traj is None else traj[0],
        "traj_err_pct": None if traj is None else traj[1],
        "vel_err_mid": None if vel is None else vel[0],
        "vel_err_last": None if vel is None else vel[1],
        "load": None,
    }


def score_results(folder: Path) -> list[dict[str, Any]]:
    """Rows for the models a pipeline results folder holds: results/<dataset>/<scene>/ratio<r>,
    or one of its ablation/<variant> folders (the split and scene are found above it)."""
    ratio_dir = next((d for d in (folder, *folder.parents) if (d / "split.h5").is_file()), None)
    if ratio_dir is None or not (ratio_dir.parent / "scene.h5").is_file():
        raise MogafError(
            f"{folder}: no split.h5 and scene.h5 above it (--score takes a results/<dataset>/<scene>/ratio<r> "
            "folder or an ablation folder in it)"
        )
    scene_h5, split_h5 = ratio_dir.parent / "scene.h5", ratio_dir / "split.h5"
    models = [folder / n for n in ("recon.h5", "refined.h5") if (folder / n).is_file()]
    if not models:
        raise MogafError(f"{folder}: holds neither recon.h5 nor refined.h5")
    return [score_model(str(m.relative_to(ratio_dir.parent.parent)), scene_h5, split_h5, m) for m in models]


def _fmt(v: Any, spec: str) -> str:
    return format(v, spec) if v is not None else "-".rjust(int(spec.split(".")[0]))


def print_table(rows: list[dict[str, Any]]) -> None:
    head = (
        f"{'scene':28s} {'ratio':>5s} {'iters':>6s} {'gauss':>7s} {'wall s':>7s} {'train':>6s} {'heldout':>7s} "
        f"{'h-mPSNR':>7s} {'unseen%':>7s} {'traj err':>9s} {'traj %':>6s} {'vel mid':>8s} {'vel last':>8s} {'load':>9s}"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        load = "-" if r["load"] is None else f"{r['load'][0]:4.1f}/{r['load'][1]:<4.1f}"
        print(
            f"{r['scene']:28s} {r['ratio']:5.2f} {r['iterations']:6d} {r['gaussians']:7d} {_fmt(r['wall_s'], '7.1f')} "
            f"{r['train_psnr']:6.2f} {r['heldout_psnr']:7.2f} {_fmt(r['heldout_mpsnr'], '7.2f')} "
            f"{_fmt(r['unseen_pct'], '7.1f')} {_fmt(r['traj_err'], '9.4f')} {_fmt(r['traj_err_pct'], '6.2f')} "
            f"{_fmt(r.get('vel_err_mid'), '8.4f')} {_fmt(r.get('vel_err_last'), '8.4f')} {load:>9s}"
        )
    print(
        "PSNR in dB; held-out = evaluation_observed frames; h-mPSNR with the co-visibility mask; unseen% = held-out "
        "pixels the training camera never sees (outside that mask); traj err in scene units (synthetic: metres) and % "
        "of the GT points' bounding-box diagonal; vel mid / vel last = error of the per-step displacement (scene units) "
        "over the middle half of the observed steps / at the last one; load = 1-min load average at start/end."
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m mogaf.bench recon", description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--cases",
        default="synthetic," + ",".join(f"mujoco/{s}" for s in MUJOCO),
        help="comma-separated: synthetic, synthetic:hard, mujoco/<scene>",
    )
    ap.add_argument("--workdir", default=None, help="inputs and outputs (default: <cache>/bench_recon)")
    ap.add_argument(
        "--params", default="{}", help="JSON recon parameters for every case (e.g. '{\"iterations\": 500}')"
    )
    ap.add_argument("--mujoco-params", default="{}", help="extra JSON parameters for the MuJoCo cases")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--progress", action="store_true")
    ap.add_argument("--json", default=None, help="also write the rows to this JSON file")
    ap.add_argument(
        "--score",
        action="append",
        default=[],
        metavar="RESULTS_DIR",
        help="train nothing: score the recon.h5 / refined.h5 of a results/<dataset>/<scene>/ratio<r> folder",
    )
    args = ap.parse_args(argv)
    if args.score:
        try:
            rows = [row for folder in args.score for row in score_results(Path(folder))]
        except MogafError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
        print_table(rows)
        _write_rows(args.json, rows)
        return 0

    # every flag checked before the first case trains (minutes each)
    params = _json_object(ap, "--params", args.params)
    mujoco_params = _json_object(ap, "--mujoco-params", args.mujoco_params)
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    unknown = [c for c in cases if not (c.startswith("synthetic") or c.startswith("mujoco/"))]
    if not cases or unknown:
        ap.error(f"--cases {args.cases!r}: give synthetic[:PRESET] and/or mujoco/SCENE, comma-separated")
    if args.json:
        try:
            check_writable(args.json)
        except MogafError as exc:
            ap.error(str(exc))
    work = Path(args.workdir) if args.workdir else cache_dir("bench_recon")
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for case in cases:
        if case.startswith("synthetic"):
            preset = case.split(":", 1)[1] if ":" in case else "default"
            inputs = _prepare_synthetic(work, preset)
            p = dict(params)
        elif case.startswith("mujoco/"):
            inputs = _prepare_mujoco(work, case.split("/", 1)[1])
            if inputs is None:
                print(f"skipping {case}: {SHARED / 'mujoco'} is absent", file=sys.stderr)
                continue
            p = {**params, **mujoco_params}
        print(f"[{case}] running recon ...", file=sys.stderr, flush=True)
        rows.append(run_case(case, inputs, work, p, args.seed, args.progress))
        print_table(rows[-1:])
    print()
    print_table(rows)
    _write_rows(args.json, rows)
    return 0


def _json_object(ap: argparse.ArgumentParser, flag: str, text: str) -> dict[str, Any]:
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        ap.error(f"{flag} is not JSON ({exc})")
    if not isinstance(value, dict):
        ap.error(f"{flag} must be a JSON object of recon settings, got {text!r}")
    return value


def _write_rows(path: str | None, rows: list[dict[str, Any]]) -> None:
    if path:
        with atomic_path(path) as tmp:
            tmp.write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    sys.exit(main())
