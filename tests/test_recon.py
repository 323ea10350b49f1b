"""Reconstruction stage on tiny scenes rendered here (no shared data needed).

A scene of Gaussians (a static back wall + a small cluster that translates)
is rendered with mogaf.render into a DyCheck-layout Scene: a moving train
camera (0) and a held-out one (1), depth, masks; priors.h5 is written
directly (the observed frames' masks, depth and the cluster's 2D tracks).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from mogaf.artefact import read_artefact, write_artefact
from mogaf.scene import SPLIT_CODES, Scene, save_scene
from mogaf.split import read_split, split_scene, write_split

W, H, T = 32, 24, 8
TINY_PARAMS = {
    "iterations": 30,
    "num_fg_init": 120,
    "num_bg_init": 150,
    "max_gaussians": 600,
    "init_optim_iters": 20,
    "num_bases": 3,
    "warmup_steps": 8,
    "control_every": 8,
    "checkpoint_every": 10,
    "log_every": 5,
    "track_targets": 1,
}


def _camera(x: float, y: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    K = np.array([[30.0, 0, W / 2], [0, 30.0, H / 2], [0, 0, 1]])
    w2c = np.eye(4)
    w2c[:3, 3] = [-x, -y, 3.0]  # camera centre (x, y, -3), looking along +z
    return K, w2c


def _tiny_world(rng: np.random.Generator, motion: float):
    gy, gx = np.meshgrid(np.linspace(-1.0, 1.0, 10), np.linspace(-1.3, 1.3, 13), indexing="ij")
    bg = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, 1.0)], 1)
    fg = rng.uniform(-0.25, 0.25, size=(40, 3))
    cols = np.concatenate([rng.uniform(0.1, 0.9, size=(len(bg), 3)), rng.uniform(0.1, 0.9, size=(len(fg), 3))])
    scales = np.concatenate([np.full((len(bg), 3), 0.12), np.full((len(fg), 3), 0.07)])

    def fg_at(t: int) -> np.ndarray:
        return fg + motion * np.array([0.06 * t, 0.03 * t, 0.0])

    return bg, fg_at, cols, scales


def _render(points: np.ndarray, cols: np.ndarray, scales: np.ndarray, is_fg: np.ndarray, K, w2c):
    from mogaf.render import rasterize

    n = len(points)
    feats = torch.tensor(np.concatenate([cols, is_fg[:, None]], 1), dtype=torch.float32)
    out = rasterize(
        torch.tensor(points, dtype=torch.float32), torch.tensor([[1.0, 0, 0, 0]] * n), torch.tensor(scales, dtype=torch.float32),
        torch.full((n,), 0.95), feats, torch.tensor(w2c, dtype=torch.float32), torch.tensor(K, dtype=torch.float32), W, H,
        background=torch.tensor([1.0, 1.0, 1.0, 0.0]),
    )
    img = out.features[..., :3].clamp(0, 1).numpy()
    mask = out.features[..., 3].numpy() > 0.5
    depth = out.depth[..., 0].numpy()
    return img, mask, depth


def make_tiny_scene(folder: Path, *, motion: float = 1.0, train_sweep: float = 0.3, seed: int = 0) -> tuple[Path, Path, Path]:
    """scene.h5, split.h5 (ratio 0.5: 4 observed steps) and priors.h5 of a tiny rendered scene."""
    rng = np.random.default_rng(seed)
    bg, fg_at, cols, scales = _tiny_world(rng, motion)
    names, images, Ks, w2cs, times, tidx, cams, splits, depths, masks = [], [], [], [], [], [], [], [], [], []
    for t in range(T):
        pts = np.concatenate([bg, fg_at(t)])
        is_fg = np.concatenate([np.zeros(len(bg)), np.ones(len(fg_at(t)))])
        for cam in (0, 1):
            x = (-train_sweep + 2 * train_sweep * t / (T - 1)) if cam == 0 else 0.4
            K, w2c = _camera(x, 0.0 if cam == 0 else 0.1)
            img, mask, depth = _render(pts, cols, scales, is_fg, K, w2c)
            names.append(f"{cam}_{t:05d}")
            images.append((img * 255).round().astype(np.uint8))
            Ks.append(K)
            w2cs.append(w2c)
            times.append(t / (T - 1))
            tidx.append(t)
            cams.append(cam)
            splits.append(SPLIT_CODES["train"] if cam == 0 else SPLIT_CODES["val"])
            depths.append(depth.astype(np.float32))
            masks.append(mask)
    scene = Scene(
        dataset="test", name="tiny", layout="iphone", frame_names=names, images=np.stack(images), K=np.stack(Ks),
        w2c=np.stack(w2cs), time=np.array(times), time_index=np.array(tidx), num_timesteps=T, camera_id=np.array(cams),
        source_split=np.array(splits, dtype=np.int8), meta={"background": [1.0, 1.0, 1.0]},
    )
    folder.mkdir(parents=True, exist_ok=True)
    scene_h5 = save_scene(folder / "scene.h5", scene, config_digest="tiny")
    split = split_scene(scene_h5, 0.5)
    split_h5 = write_split(folder / "split.h5", split)
    obs = split.frame_ids["observed"]
    # priors of the observed frames only: masks, depth, tracks of the moving cluster
    P = len(fg_at(0))
    xy = np.zeros((P, len(obs), 2), np.float32)
    for j, f in enumerate(obs):
        p = fg_at(int(tidx[f]))
        cam = p @ w2cs[f][:3, :3].T + w2cs[f][:3, 3]
        uvw = cam @ Ks[f].T
        xy[:, j] = uvw[:, :2] / uvw[:, 2:]
    priors = {
        "frame_ids": obs,
        "timesteps": np.array([tidx[f] for f in obs]),
        "masks": {"foreground": np.stack([masks[f] for f in obs]).astype(np.uint8)},
        "depth": {"values": np.stack([depths[f] for f in obs]), "valid": np.ones((len(obs), H, W), np.uint8)},
        "tracks": {"query_index": np.zeros(P, np.int64), "xy": xy, "visible": np.ones((P, len(obs)), np.uint8)},
    }
    priors_h5 = write_artefact(folder / "priors.h5", "priors", priors, config_digest="tiny", attrs={"depth_kind": "depth"})
    return scene_h5, split_h5, priors_h5


def read_arrays(path: Path) -> dict[str, np.ndarray]:
    out = {}
    with h5py.File(path, "r") as fh:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                out[name] = obj[()]
        fh.visititems(visit)
    return out


def assert_same_arrays(a: Path, b: Path) -> None:
    A, B = read_arrays(a), read_arrays(b)
    assert sorted(A) == sorted(B)
    for k in A:
        np.testing.assert_array_equal(A[k], B[k], err_msg=k)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return make_tiny_scene(tmp_path_factory.mktemp("tiny"))


@pytest.fixture(scope="module")
def tiny_run(tiny, tmp_path_factory):
    from mogaf.recon import run_recon_stage

    out = tmp_path_factory.mktemp("run") / "recon.h5"
    run_recon_stage(*tiny, out, TINY_PARAMS, seed=3, progress=False)
    return out


def test_output_schema(tiny, tiny_run):
    from mogaf.representation import load_model

    m = load_model(tiny_run)
    split = read_split(tiny[1])
    N = len(m.fg)
    assert m.timesteps.tolist() == split.observed_timesteps.tolist()
    assert m.trajectory_means.shape == (N, split.num_observed_timesteps, 3)
    assert m.rot6d.shape[1] == split.num_observed_timesteps and m.motion_coef_logits.shape == (N, m.num_bases)
    assert m.bg is not None and len(m.bg) > 0
    art = read_artefact(tiny_run, "recon")
    assert art.attrs["wall_time_s"] > 0 and np.isfinite(art.attrs["train_psnr"])
    assert len(m.training["iteration"]) == TINY_PARAMS["iterations"] // TINY_PARAMS["log_every"]
    # the stored trajectories are the blended bases applied to the canonical Gaussians
    from mogaf.representation import blend_bases, deform

    coefs = torch.softmax(torch.tensor(m.motion_coef_logits), -1)
    R, t = blend_bases(coefs, torch.tensor(m.rot6d[:, 2]), torch.tensor(m.translations[:, 2]))
    means, quats = deform(torch.tensor(m.fg.means), torch.tensor(m.fg.quats), R, t)
    np.testing.assert_allclose(means.numpy(), m.trajectory_means[:, 2], atol=1e-4)
    dots = np.abs(np.sum(quats.numpy() * m.trajectory_quats[:, 2], -1))
    np.testing.assert_allclose(dots, 1.0, atol=1e-4)


def test_same_seed_same_artefact(tiny, tiny_run, tmp_path):
    from mogaf.recon import run_recon_stage

    again = run_recon_stage(*tiny, tmp_path / "again.h5", TINY_PARAMS, seed=3, progress=False)
    assert_same_arrays(tiny_run, again)


def test_future_frames_are_never_read(tiny, tiny_run, tmp_path):
    """Poison every future row of scene.h5 (noise images, NaN cameras): same artefact."""
    import shutil

    from mogaf.recon import run_recon_stage

    scene_h5 = tmp_path / "scene.h5"
    shutil.copy(tiny[0], scene_h5)
    split = read_split(tiny[1])
    future = np.concatenate([split.frame_ids["evaluation"], split.frame_ids["train_future"]])
    assert future.size > 0
    with h5py.File(scene_h5, "r+") as fh:
        rng = np.random.default_rng(1)
        for f in future:
            fh["frames/images"][f] = rng.integers(0, 256, size=fh["frames/images"].shape[1:], dtype=np.uint8)
            fh["frames/K"][f] = np.nan
            fh["frames/w2c"][f] = np.nan
    out = run_recon_stage(scene_h5, tiny[1], tiny[2], tmp_path / "poisoned.h5", TINY_PARAMS, seed=3, progress=False)
    assert_same_arrays(tiny_run, out)


def test_resume_from_checkpoint_matches_uninterrupted(tiny, tiny_run, tmp_path):
    from mogaf.recon import run_recon_stage

    ckpt = tmp_path / "ckpt" / "recon.pt"
    # interrupted after 15 of 30 iterations (checkpoints every 10 plus one at the stop)
    run_recon_stage(*tiny, tmp_path / "unused.h5", TINY_PARAMS, seed=3, checkpoint=ckpt, progress=False, stop_at=15)
    assert ckpt.exists() and not (tmp_path / "unused.h5").exists()
    state = torch.load(ckpt, weights_only=True)
    assert state["iteration"] == 15
    out = run_recon_stage(*tiny, tmp_path / "resumed.h5", TINY_PARAMS, seed=3, checkpoint=ckpt, progress=False)
    assert not ckpt.exists()  # removed after success
    assert_same_arrays(tiny_run, out)


def test_checkpoint_of_other_settings_is_ignored(tiny, tiny_run, tmp_path):
    from mogaf.recon import run_recon_stage

    ckpt = tmp_path / "recon.pt"
    other = {**TINY_PARAMS, "num_bases": 2}
    run_recon_stage(*tiny, tmp_path / "x.h5", other, seed=3, checkpoint=ckpt, progress=False, stop_at=12)
    out = run_recon_stage(*tiny, tmp_path / "fresh.h5", TINY_PARAMS, seed=3, checkpoint=ckpt, progress=False)
    assert_same_arrays(tiny_run, out)


def test_render_model_reproduces_training_view(tiny, tiny_run):
    from mogaf.recon import render_model, render_poses
    from mogaf.representation import load_model
    from mogaf.split import load_frames

    m = load_model(tiny_run)
    fr = load_frames(tiny[0], read_split(tiny[1]), "observed")
    out = render_model(m, int(fr.time_index[1]), fr.K[1], fr.w2c[1], W, H, features="rgb+mask")
    assert out.features.shape == (H, W, 4)
    same = render_poses(m, m.trajectory_means[:, 1], m.trajectory_quats[:, 1], fr.K[1], fr.w2c[1], W, H)
    np.testing.assert_allclose(same.features.numpy(), out.features[..., :3].numpy(), atol=1e-5)
    with pytest.raises(Exception, match="not an observed step"):
        render_model(m, T - 1, fr.K[1], fr.w2c[1], W, H)


def test_stored_model_renders_as_trained_with_sh(tiny):
    """The render of a stored model (evaluation, grouping, benchmarks: mogaf.rendering)
    equals the trainer's own differentiable render, SH bands included."""
    from mogaf.recon.params import resolve_params
    from mogaf.recon.stage import build_trainer, prepare_data
    from mogaf.recon.data import load_train_data
    from mogaf.rendering import render_model

    # CPU and one rasterizer for both renders, also on a machine with CUDA
    p = resolve_params({**TINY_PARAMS, "sh_degree": 3, "iterations": 4, "device": "cpu", "backend": "torch"})
    split = read_split(tiny[1])
    data = load_train_data(tiny[0], split, tiny[2], downscale=p["downscale"])
    prepare_data(data, p)
    trainer, _ = build_trainer(data, p, seed=3)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():  # visible view-dependent colours, as after long training
        for part in (trainer.model.fg, trainer.model.bg):
            if part is not None and "sh_rest" in part.params:
                sh = part.params["sh_rest"]
                sh.copy_(0.5 * torch.randn(sh.shape, generator=gen))
        f = 1
        trained = trainer.render_frame(f, with_mask=False)[0].features[..., :3].numpy()
    model = trainer.model.to_model4d(split.observed_timesteps, data.background)
    t = int(split.observed_timesteps[int(trainer.tidx[f])])
    stored = render_model(model, t, trainer.K[f], trainer.w2c[f], trainer.W, trainer.H, backend="torch").features.numpy()
    assert model.sh_degree == 3 and model.fg.sh_rest is not None
    np.testing.assert_allclose(stored, trained, atol=1e-4)
    plain = dataclasses.replace(model, sh_degree=0, fg=dataclasses.replace(model.fg, sh_rest=None),
                                bg=None if model.bg is None else dataclasses.replace(model.bg, sh_rest=None))
    assert np.abs(render_model(plain, t, trainer.K[f], trainer.w2c[f], trainer.W, trainer.H, backend="torch").features.numpy()
                  - stored).max() > 0.05


def test_load_model_refuses_sh_bands_of_another_degree(tiny_run, tmp_path):
    """A stored model whose sh_rest does not match its sh_degree fails on load, naming the entry."""
    import shutil

    from mogaf.errors import MogafError
    from mogaf.representation import load_model

    bad = tmp_path / "recon.h5"
    shutil.copy(tiny_run, bad)
    with h5py.File(bad, "r+") as fh:
        fh.attrs["sh_degree"] = 2  # the tiny model is stored at degree 0, without sh_rest
    with pytest.raises(MogafError, match="fg/sh_rest.*0 SH coefficients.*expected 8 for sh_degree 2"):
        load_model(bad)


def test_static_scene_psnr_rises(tmp_path):
    """Training must improve a sparse, translucent start substantially (this can fail)."""
    from mogaf.recon import run_recon_stage
    from mogaf.representation import load_model

    inputs = make_tiny_scene(tmp_path / "static", motion=0.0, train_sweep=0.5, seed=5)
    params = {**TINY_PARAMS, "iterations": 150, "num_fg_init": 30, "num_bg_init": 40, "init_opacity": 0.2,
              "log_every": 10, "warmup_steps": 30, "control_every": 30}
    out = run_recon_stage(*inputs, tmp_path / "static.h5", params, seed=0, progress=False)
    psnr = load_model(out).training["psnr"]
    assert psnr[-3:].mean() > psnr[0] + 6.0, psnr
    assert read_artefact(out, "recon").attrs["train_psnr"] > 22.0
