"""A tiny scene rendered with mogaf.render, for the reconstruction stage (no shared data needed).

A scene of Gaussians (a static back wall + a small cluster that translates)
is rendered into a DyCheck-layout Scene: a moving train camera (0) and a
held-out one (1), depth, masks; priors.h5 is written directly (the observed
frames' masks, depth and the cluster's 2D tracks). TINY_PARAMS: a
reconstruction budget small enough for the tests.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import torch

from mogaf.artefact import write_artefact
from mogaf.scene import SPLIT_CODES, Scene, save_scene
from mogaf.split import split_scene, write_split

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
        torch.tensor(points, dtype=torch.float32),
        torch.tensor([[1.0, 0, 0, 0]] * n),
        torch.tensor(scales, dtype=torch.float32),
        torch.full((n,), 0.95),
        feats,
        torch.tensor(w2c, dtype=torch.float32),
        torch.tensor(K, dtype=torch.float32),
        W,
        H,
        background=torch.tensor([1.0, 1.0, 1.0, 0.0]),
    )
    img = out.features[..., :3].clamp(0, 1).numpy()
    mask = out.features[..., 3].numpy() > 0.5
    depth = out.depth[..., 0].numpy()
    return img, mask, depth


def make_tiny_scene(
    folder: Path, *, motion: float = 1.0, train_sweep: float = 0.3, seed: int = 0
) -> tuple[Path, Path, Path]:
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
        dataset="test",
        name="tiny",
        layout="iphone",
        frame_names=names,
        images=np.stack(images),
        K=np.stack(Ks),
        w2c=np.stack(w2cs),
        time=np.array(times),
        time_index=np.array(tidx),
        num_timesteps=T,
        camera_id=np.array(cams),
        source_split=np.array(splits, dtype=np.int8),
        meta={"background": [1.0, 1.0, 1.0]},
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
    priors_h5 = write_artefact(
        folder / "priors.h5", "priors", priors, config_digest="tiny", attrs={"depth_kind": "depth"}
    )
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


def perturbed_checkpoint(src: Path, dst: Path) -> None:
    """A copy of a training checkpoint with its Gaussians' means moved: a run
    resumed from it must differ from one resumed from `src` (it was loaded)."""
    import torch

    from mogaf.recon.checkpoint import save_checkpoint

    state = torch.load(src, map_location="cpu", weights_only=True)
    state["model"]["fg.means"] = state["model"]["fg.means"] + 0.05
    save_checkpoint(dst, state)


def differs(a: Path, b: Path) -> bool:
    """Whether two artefacts differ in any array."""
    A, B = read_arrays(a), read_arrays(b)
    return sorted(A) != sorted(B) or any(not np.array_equal(A[k], B[k]) for k in A)
