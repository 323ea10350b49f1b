"""Reconstruction stage on tiny rendered scenes (support.tiny_scene; no shared data needed)."""

from __future__ import annotations

import dataclasses
import logging

import h5py
import numpy as np
import pytest
import torch

from mogaf.artefact import read_artefact
from mogaf.split import read_split
from support.tiny_scene import TINY_PARAMS, H, T, W, assert_same_arrays, differs, make_tiny_scene, perturbed_checkpoint


@pytest.fixture(scope="module")
def tiny_run(tiny_scene, tmp_path_factory):
    from mogaf.recon.stage import run_recon_stage

    out = tmp_path_factory.mktemp("run") / "recon.h5"
    run_recon_stage(*tiny_scene, out, TINY_PARAMS, seed=3, progress=False)
    return out


def test_output_schema(tiny_scene, tiny_run):
    from mogaf.representation import load_model

    m = load_model(tiny_run)
    split = read_split(tiny_scene[1])
    N = len(m.fg)
    assert m.timesteps.tolist() == split.observed_timesteps.tolist()
    assert m.trajectory_means.shape == (N, split.num_observed_timesteps, 3)
    assert m.rot6d.shape[1] == split.num_observed_timesteps and m.motion_coef_logits.shape == (N, m.num_bases)
    assert m.bg is not None and len(m.bg) > 0
    art = read_artefact(tiny_run, "recon")
    assert art.attrs["wall_time_s"] > 0 and np.isfinite(art.attrs["train_psnr"])
    assert len(m.training["iteration"]) == TINY_PARAMS["iterations"] // TINY_PARAMS["log_every"]
    # the stored trajectories are the blended bases applied to the canonical Gaussians
    from mogaf.representation import blend_bases

    coefs = torch.softmax(torch.tensor(m.motion_coef_logits), -1)
    R, t = blend_bases(coefs, torch.tensor(m.rot6d[:, 2]), torch.tensor(m.translations[:, 2]))
    means, quats = _deform(torch.tensor(m.fg.means), torch.tensor(m.fg.quats), R, t)
    np.testing.assert_allclose(means.numpy(), m.trajectory_means[:, 2], atol=1e-4)
    dots = np.abs(np.sum(quats.numpy() * m.trajectory_quats[:, 2], -1))
    np.testing.assert_allclose(dots, 1.0, atol=1e-4)


def test_time_breakdown_splits_the_training_steps(tiny_run):
    """recon.h5 says where its training steps' time went: the rasterizer's kernels
    (timed inside the C++ calls) and the rest, each a part of the steps' total."""
    from mogaf.render import cpu

    t = read_artefact(tiny_run, "recon").attrs["time_breakdown_s"]
    parts = ["rasterizer_forward", "rasterizer_backward", "kernel_build", "render_other", "autograd_other"]
    parts += ["optimizer", "density_control", "losses_and_other"]
    assert set(parts) | {"init", "steps_total", "training_psnr_and_model"} == set(t)
    if cpu.available():
        assert t["rasterizer_forward"] > 0 and t["rasterizer_backward"] > 0
    assert all(t[k] >= 0 for k in parts) and sum(t[k] for k in parts) == pytest.approx(t["steps_total"], abs=0.01)
    # every timer ran (the remainder, losses_and_other, is the total minus the timed parts)
    assert all(t[k] > 0 for k in ("render_other", "autograd_other", "optimizer", "steps_total")), t


def test_same_seed_same_artefact(tiny_scene, tiny_run, tmp_path):
    from mogaf.recon.stage import run_recon_stage

    again = run_recon_stage(*tiny_scene, tmp_path / "again.h5", TINY_PARAMS, seed=3, progress=False)
    assert_same_arrays(tiny_run, again)


def test_smooth_bases_prior_reaches_the_training(tiny_scene, tiny_run, tmp_path):
    """recon.smooth_bases "jerk" changes the reconstruction (its default is
    SoM's acceleration prior) and is recorded with its parameters."""
    from mogaf.recon.stage import run_recon_stage

    params = {**TINY_PARAMS, "smooth_bases": "jerk"}
    out = run_recon_stage(*tiny_scene, tmp_path / "jerk.h5", params, seed=3, progress=False)
    assert differs(tiny_run, out)
    assert read_artefact(out, "recon").attrs["params"]["smooth_bases"] == "jerk"
    assert read_artefact(tiny_run, "recon").attrs["params"]["smooth_bases"] == "acceleration"


def test_speed_prior_slows_the_reconstructed_motion(tiny_scene, tiny_run, tmp_path):
    """recon.w_speed > 0 (its default 0 is SoM's training, unchanged: the
    tiny run's params record 0) adds the foreground's mean speed to the loss:
    the same training with it moves the Gaussians less between steps."""
    from mogaf.recon.stage import run_recon_stage
    from mogaf.representation import load_model

    out = run_recon_stage(*tiny_scene, tmp_path / "speed.h5", {**TINY_PARAMS, "w_speed": 10.0}, seed=3, progress=False)
    assert read_artefact(out, "recon").attrs["params"]["w_speed"] == 10.0
    assert read_artefact(tiny_run, "recon").attrs["params"]["w_speed"] == 0.0

    def mean_speed(path):
        means = load_model(path).trajectory_means.astype(np.float64)
        return float(np.linalg.norm(np.diff(means, axis=1), axis=-1).mean())

    assert mean_speed(out) < 0.9 * mean_speed(tiny_run)  # 0.83 at 30 steps


def test_isometry_prior_keeps_neighbours_at_their_distances(tiny_scene, tiny_run, tmp_path):
    """recon.w_isometry > 0 (default 0, SoM's training unchanged) adds the
    change of each fg Gaussian's distances to its canonical neighbours between
    neighbouring steps: the same training with it stretches the set less."""
    from mogaf.recon.losses import nearest_neighbours, pair_distances
    from mogaf.recon.stage import run_recon_stage
    from mogaf.representation import load_model

    params = {**TINY_PARAMS, "w_isometry": 10.0}
    out = run_recon_stage(*tiny_scene, tmp_path / "isometry.h5", params, seed=3, progress=False)
    assert read_artefact(out, "recon").attrs["params"]["w_isometry"] == 10.0
    assert read_artefact(tiny_run, "recon").attrs["params"]["w_isometry"] == 0.0

    def mean_stretch(path):
        means = torch.from_numpy(load_model(path).trajectory_means.astype(np.float64))
        nbrs = nearest_neighbours(means[:, 0], 8)
        d = torch.stack([pair_distances(means[:, k], nbrs, 0.0) for k in range(means.shape[1])])
        return float((d[1:] - d[:-1]).abs().mean())

    assert mean_stretch(out) < 0.9 * mean_stretch(tiny_run)  # 0.61 at 30 steps
    # the neighbours are checkpointed: rebuilt from a later step's means at the resume they would differ
    ckpt = tmp_path / "ckpt" / "recon.pt"
    run_recon_stage(*tiny_scene, tmp_path / "unused.h5", params, seed=3, checkpoint=ckpt, progress=False, stop_at=15)
    resumed = run_recon_stage(*tiny_scene, tmp_path / "resumed.h5", params, seed=3, checkpoint=ckpt, progress=False)
    assert_same_arrays(out, resumed)


def test_future_frames_are_never_read(tiny_scene, tiny_run, tmp_path):
    """Poison every future row of scene.h5 (noise images, NaN cameras): same artefact."""
    import shutil

    from mogaf.recon.stage import run_recon_stage

    scene_h5 = tmp_path / "scene.h5"
    shutil.copy(tiny_scene[0], scene_h5)
    split = read_split(tiny_scene[1])
    future = np.concatenate([split.frame_ids["evaluation"], split.frame_ids["train_future"]])
    assert future.size > 0
    with h5py.File(scene_h5, "r+") as fh:
        rng = np.random.default_rng(1)
        for f in future:
            fh["frames/images"][f] = rng.integers(0, 256, size=fh["frames/images"].shape[1:], dtype=np.uint8)
            fh["frames/K"][f] = np.nan
            fh["frames/w2c"][f] = np.nan
    out = run_recon_stage(
        scene_h5, tiny_scene[1], tiny_scene[2], tmp_path / "poisoned.h5", TINY_PARAMS, seed=3, progress=False
    )
    assert_same_arrays(tiny_run, out)


def test_resume_from_checkpoint_matches_uninterrupted(tiny_scene, tiny_run, tmp_path, caplog):
    from mogaf.recon.stage import run_recon_stage

    ckpt = tmp_path / "ckpt" / "recon.pt"
    # interrupted after 15 of 30 iterations (checkpoints every 10 plus one at the stop)
    run_recon_stage(
        *tiny_scene, tmp_path / "unused.h5", TINY_PARAMS, seed=3, checkpoint=ckpt, progress=False, stop_at=15
    )
    assert ckpt.exists() and not (tmp_path / "unused.h5").exists()
    state = torch.load(ckpt, weights_only=True)
    assert state["iteration"] == 15
    moved = tmp_path / "moved.pt"
    perturbed_checkpoint(ckpt, moved)
    with caplog.at_level(logging.INFO, logger="mogaf"):
        out = run_recon_stage(
            *tiny_scene, tmp_path / "resumed.h5", TINY_PARAMS, seed=3, checkpoint=ckpt, progress=False
        )
    assert f"recon: resumed from {ckpt} at iteration 15 of 30" in caplog.text
    assert not ckpt.exists()  # removed after success
    assert_same_arrays(tiny_run, out)
    # the state is read from the checkpoint, not recomputed: moved means give another model
    other = run_recon_stage(*tiny_scene, tmp_path / "moved.h5", TINY_PARAMS, seed=3, checkpoint=moved, progress=False)
    assert differs(out, other)


def test_checkpoint_of_other_settings_is_ignored(tiny_scene, tiny_run, tmp_path, caplog):
    from mogaf.recon.stage import run_recon_stage

    ckpt = tmp_path / "recon.pt"
    other = {**TINY_PARAMS, "num_bases": 2}
    run_recon_stage(*tiny_scene, tmp_path / "x.h5", other, seed=3, checkpoint=ckpt, progress=False, stop_at=12)
    with caplog.at_level(logging.INFO, logger="mogaf"):
        out = run_recon_stage(*tiny_scene, tmp_path / "fresh.h5", TINY_PARAMS, seed=3, checkpoint=ckpt, progress=False)
    assert "resumed from" not in caplog.text
    assert_same_arrays(tiny_run, out)


def test_render_model_reproduces_training_view(tiny_scene, tiny_run):
    from mogaf.rendering import render_model, render_poses
    from mogaf.representation import load_model
    from mogaf.split import load_frames

    m = load_model(tiny_run)
    fr = load_frames(tiny_scene[0], read_split(tiny_scene[1]), "observed")
    out = render_model(m, int(fr.time_index[1]), fr.K[1], fr.w2c[1], W, H, features="rgb+mask")
    assert out.features.shape == (H, W, 4)
    same = render_poses(m, m.trajectory_means[:, 1], m.trajectory_quats[:, 1], fr.K[1], fr.w2c[1], W, H)
    np.testing.assert_allclose(same.features.numpy(), out.features[..., :3].numpy(), atol=1e-5)
    with pytest.raises(Exception, match="not an observed step"):
        render_model(m, T - 1, fr.K[1], fr.w2c[1], W, H)
    # the trained view: closer to its own image at its own time than at the other observed times
    target = torch.tensor(fr.images[1], dtype=torch.float32) / 255.0
    err = {
        t: float((render_model(m, t, fr.K[1], fr.w2c[1], W, H).features - target).square().mean())
        for t in range(m.trajectory_means.shape[1])
    }
    assert min(err, key=err.get) == int(fr.time_index[1]), err


def test_stored_model_renders_as_trained_with_sh(tiny_scene):
    """The render of a stored model (evaluation, grouping, benchmarks: mogaf.rendering)
    equals the trainer's own differentiable render, SH bands included."""
    from mogaf.recon.data import load_train_data
    from mogaf.recon.params import resolve_params
    from mogaf.recon.stage import build_trainer, prepare_data
    from mogaf.rendering import render_model

    # CPU and one rasterizer for both renders, also on a machine with CUDA
    p = resolve_params({**TINY_PARAMS, "sh_degree": 3, "iterations": 4, "device": "cpu", "backend": "torch"})
    split = read_split(tiny_scene[1])
    data = load_train_data(tiny_scene[0], split, tiny_scene[2], downscale=p["downscale"])
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
    stored = render_model(
        model, t, trainer.K[f], trainer.w2c[f], trainer.W, trainer.H, backend="torch"
    ).features.numpy()
    assert model.sh_degree == 3 and model.fg.sh_rest is not None
    np.testing.assert_allclose(stored, trained, atol=1e-4)
    plain = dataclasses.replace(
        model,
        sh_degree=0,
        fg=dataclasses.replace(model.fg, sh_rest=None),
        bg=None if model.bg is None else dataclasses.replace(model.bg, sh_rest=None),
    )
    assert (
        np.abs(
            render_model(plain, t, trainer.K[f], trainer.w2c[f], trainer.W, trainer.H, backend="torch").features.numpy()
            - stored
        ).max()
        > 0.05
    )


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
    from mogaf.recon.stage import run_recon_stage
    from mogaf.representation import load_model

    inputs = make_tiny_scene(tmp_path / "static", motion=0.0, train_sweep=0.5, seed=5)
    params = {
        **TINY_PARAMS,
        "iterations": 150,
        "num_fg_init": 30,
        "num_bg_init": 40,
        "init_opacity": 0.2,
        "log_every": 10,
        "warmup_steps": 30,
        "control_every": 30,
    }
    out = run_recon_stage(*inputs, tmp_path / "static.h5", params, seed=0, progress=False)
    psnr = load_model(out).training["psnr"]
    assert psnr[-3:].mean() > psnr[0] + 6.0, psnr
    assert read_artefact(out, "recon").attrs["train_psnr"] > 22.0


@pytest.mark.gpu
@pytest.mark.parametrize("extra", [{}, {"curriculum": "on", "silhouette": "on"}])
def test_recon_on_cuda_matches_the_cpu_run(tiny_scene, tmp_path, extra):
    """The whole training step on CUDA (gsplat, the losses, densification and,
    with the curriculum and silhouettes on, their paths too): a finite model
    whose fit to the training frames is close to the CPU run's."""
    if not torch.cuda.is_available():
        pytest.skip("needs CUDA")
    pytest.importorskip("gsplat")
    from mogaf.recon.stage import run_recon_stage

    params = {**TINY_PARAMS, **extra}
    cpu = run_recon_stage(*tiny_scene, tmp_path / "cpu.h5", {**params, "device": "cpu"}, seed=3, progress=False)
    gpu = run_recon_stage(*tiny_scene, tmp_path / "gpu.h5", {**params, "device": "cuda"}, seed=3, progress=False)
    a, b = read_artefact(cpu, "recon"), read_artefact(gpu, "recon")
    assert np.isfinite(b["trajectories/means"]).all()
    assert abs(a.attrs["train_psnr"] - b.attrs["train_psnr"]) < 1.5, (a.attrs["train_psnr"], b.attrs["train_psnr"])


def _deform(
    means: torch.Tensor, quats: torch.Tensor, R: torch.Tensor, t: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Apply per-Gaussian rigid transforms (N,3,3),(N,3) to canonical poses."""
    from mogaf.representation import matrix_to_quat, quat_to_matrix

    means_t = torch.einsum("nij,nj->ni", R, means) + t
    quats_t = matrix_to_quat(R @ quat_to_matrix(quats))
    return means_t, quats_t
