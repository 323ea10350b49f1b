"""Optimisation loop of the reconstruction stage.

One step: sample `batch_size` observed frames (a seeded torch.Generator),
pose the fg Gaussians at each frame's step, render colour (+ fg-share
channel when there is a background model, + positions at a few target
frames for the 2D track loss) in one rasterizer pass, add the losses,
backpropagate, take one Adam step per parameter, accumulate the
screen-space gradient statistics and, every `control_every` steps,
densify / prune.

Determinism: every random choice goes through one torch.Generator (frames,
track targets, split positions) seeded from `seed`; its state is part of the
checkpoint, as are the parameters, the Adam moments, the density
statistics and the training curve, so a resumed run continues bit for bit.

Beside it: schedule.py (learning rates, curriculum, gap filling) and
frame_losses.py (track and silhouette terms), mixed into Trainer, and
checkpoint.py (the checkpoint files and the training curve).
"""

from __future__ import annotations

import math
import os
import time
from typing import Any

import numpy as np
import torch

from ..camera import camera_centers
from ..devices import resolve_device
from ..optim import Adam
from ..progress import Progress
from ..rendering import rasterize
from ..timing import KERNELS, PhaseClock
from .checkpoint import CHECKPOINT_VERSION, Curve, load_checkpoint, save_checkpoint  # noqa: F401  (load_checkpoint re-exported)
from .data import TrainData
from .densify import DensifyRules, DensityStats, control_step
from .frame_losses import FrameLosses
from .init_common import InitResult
from .interpolation import gap_interpolation
from .losses import (
    basis_smoothness,
    gradient_loss,
    last_dim_variance,
    masked_l1,
    nearest_neighbours,
    pair_distances,
    rgb_loss,
    z_velocity_loss,
)
from .model import ReconModel, gaussian_colors
from .params import load_settings
from .schedule import TrainerSchedule, _lr_names
from .silhouette import SilhouetteTargets


class Trainer(TrainerSchedule, FrameLosses):
    def __init__(
        self,
        data: TrainData,
        params: dict,
        seed: int,
        init: InitResult | None = None,
        state: dict | None = None,
        coarse: TrainData | None = None,
    ):
        self.fine = data
        self.coarse = coarse
        params = load_settings(params)
        self.p = params
        self.seed = int(seed)
        self.dev = resolve_device(params.device, "recon")
        d = self.dev
        self.w2c = torch.tensor(data.w2c, dtype=torch.float32, device=d)
        self.cam_centers = torch.tensor(camera_centers(data.w2c), dtype=torch.float32, device=d)
        self.tidx = torch.tensor(data.tidx, dtype=torch.int64)  # CPU: sampling logic
        self.background = torch.tensor(data.background, dtype=torch.float32, device=d)
        self.tracks_vis = torch.tensor(data.tracks_visible, device=d) if data.has_tracks else None
        # coarse-to-fine: the first `coarse_fraction` of the iterations use `coarse`
        self.switch_at = int(params.coarse_fraction * params.iterations) if coarse is not None else 0
        self._levels: dict[int, dict[str, Any]] = {}
        self.level = -1
        self.gen = torch.Generator().manual_seed(self.seed)
        if state is None:
            assert init is not None
            self.model = ReconModel(
                init.fg, init.rot6d, init.transl, init.bg, sh_degree=params.sh_degree, scene_scale=init.scene_scale
            )
            self.canonical_frame = init.canonical_frame
            self.motion_source = init.motion_source
            self.init_info = dict(init.info)
            self.iteration = 0
            self.curve = Curve()
            self.elapsed = 0.0
        else:
            self.model = ReconModel.from_state(
                state["model"], sh_degree=params.sh_degree, scene_scale=float(state["scene_scale"])
            )
            self.canonical_frame = int(state["canonical_frame"])
            self.motion_source = str(state["motion_source"])
            self.init_info = dict(state.get("init_info", {}))
            self.iteration = int(state["iteration"])
            self.curve = Curve(**state["curve"])
            self.elapsed = float(state["elapsed"])
            self.gen.set_state(state["generator"])
        self.model.to(self.dev)
        self.scale = self.model.scene_scale
        self.base_lr = _lr_names(params, self.scale)
        if self.motion_source == "identity":
            for k in ("motion.rot6d", "motion.transl"):
                self.base_lr[k] *= params.lr_motion_identity_boost
        # eps 1e-15 as 3DGS's and gsplat's trainers (SoM keeps torch's 1e-8): tiny per-Gaussian gradients still step
        self.optimizers = {
            name: Adam([p], lr=self.base_lr[name], eps=1e-15) for name, p in self.model.named_tensors().items()
        }
        self.stats = DensityStats(self.model.num_gaussians)
        if state is not None:
            for name, opt in self.optimizers.items():
                opt.load_state_dict(state["optimizers"][name])
            self.stats.load(state["stats"])
        self.has_bg = self.model.bg is not None
        gi = gap_interpolation(data.num_timesteps, data.tidx) if params.gap_interpolation else None
        if gi is None:
            self.gap_fill = None
        else:
            knots = np.unique(data.tidx)
            self.gap_fill = (
                torch.tensor(gi[0], device=self.dev),
                torch.tensor(knots, device=self.dev),
                torch.tensor(gi[1], dtype=torch.float32, device=self.dev),
            )
        mode = params.curriculum
        self.curriculum = (mode == "on") or (mode == "auto" and self.motion_source == "identity")
        self.rules = DensifyRules(
            grad_threshold=params.densify_grad_threshold,
            scale_threshold=params.densify_scale_threshold,
            screen_threshold=params.densify_screen_threshold,
            cull_opacity=params.cull_opacity_threshold,
            cull_scale=params.cull_scale_threshold,
            cull_screen=params.cull_screen_threshold,
            extent=self.scale,
            max_gaussians=params.max_gaussians,
        )
        smode = params.silhouette
        self.silhouette = params.w_silhouette > 0 and (
            (smode == "on") or (smode == "auto" and self.motion_source != "procrustes")
        )
        # w_isometry's neighbour indices, checkpointed: rebuilt from the means of a later step they would differ
        self._nbrs: torch.Tensor | None = None
        if state is not None and state.get("isometry_neighbours") is not None:
            self._nbrs = state["isometry_neighbours"].to(self.dev)
        self.use_level(self.level_for(self.iteration))
        self._loss_acc: list[float] = []
        self._psnr_acc: list[float] = []
        self.clock = PhaseClock(torch.cuda.synchronize if self.dev.type == "cuda" else None)
        # extra_loss(pick, note) -> scalar: a term added once per step (the refinement's L_motion)
        self.extra_loss = None
        if state is not None:
            self._loss_acc = list(state["pending"]["loss"])
            self._psnr_acc = list(state["pending"]["psnr"])

    # -------------------------------------------------------------- resolution levels
    def level_for(self, it: int) -> int:
        return 0 if (self.coarse is not None and it < self.switch_at) else 1

    def use_level(self, level: int) -> None:
        """Point the per-resolution tensors at level 0 (coarse) or 1 (fine); built once each."""
        if level == self.level:
            return
        if level not in self._levels:
            data = self.coarse if level == 0 else self.fine
            d = self.dev
            lv: dict[str, Any] = {
                "data": data,
                "H": data.height,
                "W": data.width,
                "images": torch.tensor(data.images, device=d),
                "masks": torch.tensor(data.fg_masks, device=d),
                "K": torch.tensor(data.K, dtype=torch.float32, device=d),
                "depth": torch.tensor(data.depth, device=d) if data.has_depth else None,
                "depth_valid": torch.tensor(data.depth_valid.astype(np.float32), device=d) if data.has_depth else None,
                "tracks_xy": torch.tensor(data.tracks_xy, device=d) if data.has_tracks else None,
                "sil": None,
            }
            if self.silhouette:
                gen = torch.Generator().manual_seed(self.seed + 29 + level)
                lv["sil"] = SilhouetteTargets(data, self.p.silhouette_pixels, gen, d)
            self._levels[level] = lv
        lv = self._levels[level]
        self.level = level
        self.data = lv["data"]
        self.H, self.W = lv["H"], lv["W"]
        for k in ("images", "masks", "K", "depth", "depth_valid", "tracks_xy", "sil"):
            setattr(self, k, lv[k])

    # -------------------------------------------------------------- rendering
    def render_frame(
        self, f: int, extra_fg: torch.Tensor | None = None, extra_bg: torch.Tensor | None = None, with_mask: bool = True
    ):
        m = self.model
        t = int(self.tidx[f])
        means_fg, quats_fg = m.fg_poses_at(t)
        cam = self.cam_centers[f]
        cols_fg = gaussian_colors(m.fg.get("color_logits"), m.fg.sh_rest(), means_fg, cam)
        parts_means = [means_fg]
        parts_quats = [quats_fg]
        parts_scales = [m.fg.scales()]
        parts_op = [m.fg.opacities()]
        feats_fg = [cols_fg]
        feats_bg = []
        if self.has_bg:
            bmeans = m.bg.get("means")
            parts_means.append(bmeans)
            parts_quats.append(m.bg.quats())
            parts_scales.append(m.bg.scales())
            parts_op.append(m.bg.opacities())
            feats_bg.append(gaussian_colors(m.bg.get("color_logits"), m.bg.sh_rest(), bmeans, cam))
            if with_mask:
                feats_fg.append(torch.ones(m.num_fg, 1, device=self.dev))
                feats_bg.append(torch.zeros(m.num_bg, 1, device=self.dev))
        if extra_fg is not None:
            feats_fg.append(extra_fg)
            if self.has_bg:
                feats_bg.append(extra_bg)
        feats = torch.cat(feats_fg, 1)
        if self.has_bg:
            feats = torch.cat([feats, torch.cat(feats_bg, 1)], 0)
        C = feats.shape[1]
        bgc = torch.zeros(C, device=self.dev)
        bgc[:3] = self.background
        out = rasterize(
            torch.cat(parts_means, 0),
            torch.cat(parts_quats, 0),
            torch.cat(parts_scales, 0),
            torch.cat(parts_op, 0),
            feats,
            self.w2c[f],
            self.K[f],
            self.W,
            self.H,
            background=bgc,
            backend=self.p.backend,
        )
        if torch.is_grad_enabled() and hasattr(out, "retain_means2d_grad"):
            out.retain_means2d_grad()
        return out, means_fg

    # -------------------------------------------------------------- one step
    def step(self) -> tuple[float, float]:
        p = self.p
        it = self.iteration
        self.use_level(self.level_for(it))
        self.set_lrs(it)
        self.extrapolate_bases(it)
        allowed = self.allowed_frames(it)
        bs = min(p.batch_size, int(allowed.numel()))
        pick = allowed[torch.randperm(int(allowed.numel()), generator=self.gen)[:bs]]
        total = torch.zeros((), device=self.dev)
        terms: dict[str, float] = {}

        def note(name: str, value: torch.Tensor) -> torch.Tensor:
            terms[name] = terms.get(name, 0.0) + float(value.detach())
            return value

        outs = []
        psnrs = []
        for f in pick.tolist():
            out, loss, psnr = self._frame_loss(f, allowed, note)
            outs.append(out)
            psnrs.append(psnr)
            total = total + loss
        total = total / len(outs)
        total = total + self._regularisers(pick, note)
        self.last_terms = terms
        for opt in self.optimizers.values():
            opt.zero_grad(set_to_none=True)
        with self.clock.phase("backward"):
            total.backward()
        with self.clock.phase("density_control"):
            for out in outs:
                grad = out.means2d_grad if hasattr(out, "means2d_grad") else getattr(out.means2d, "grad", None)
                if grad is not None:
                    radii = out.radii.max(dim=-1).values if out.radii.ndim == 2 else out.radii
                    self.stats.accumulate(grad, radii, self.W, self.H, len(outs))
        with self.clock.phase("optimizer"):
            for opt in self.optimizers.values():
                opt.step()
        self.fill_gaps()
        self.iteration += 1
        with self.clock.phase("density_control"):
            self.control()
        return float(total.detach()), float(np.mean(psnrs))

    def _track_targets(self, f: int, allowed: torch.Tensor) -> torch.Tensor | None:
        """Frames (other than f) whose 2D tracks the fg Gaussians rendered at f must hit; None without tracks."""
        p = self.p
        if self.tracks_xy is None or p.w_track <= 0 or p.track_targets <= 0:
            return None
        cand = allowed[allowed != f]
        if cand.numel() == 0:
            return None
        k = min(p.track_targets, int(cand.numel()))
        return cand[torch.randperm(int(cand.numel()), generator=self.gen)[:k]]

    def _frame_loss(self, f: int, allowed: torch.Tensor, note) -> tuple[Any, torch.Tensor, float]:
        """Render frame f (with the track targets' positions as extra features) and its loss terms."""
        p = self.p
        m = self.model
        q = p.loss_quantile
        extra_fg = extra_bg = None
        targets = self._track_targets(f, allowed)
        if targets is not None:
            tt = self.tidx[targets]
            tm = m.fg_means_at(tt.to(self.dev))  # (N, k, 3)
            extra_fg = tm.reshape(m.num_fg, -1)
            if self.has_bg:
                extra_bg = m.bg.get("means").repeat(1, len(tt))
        with self.clock.phase("render"):
            out, means_f = self.render_frame(f, extra_fg, extra_bg)
        feats = out.features
        rgb = feats[..., :3]
        acc = out.alpha
        gt = self.images[f]
        fgm = self.masks[f][..., None]
        loss = p.w_rgb * note("rgb", rgb_loss(rgb[None], gt[None], p.ssim_weight))
        with torch.no_grad():
            mse = float(((rgb - gt) ** 2).mean())
            psnr = -10 * math.log10(max(mse, 1e-10))
        if p.w_mask > 0:
            if self.has_bg:
                ml = ((acc - 1) ** 2).mean() + masked_l1(feats[..., 3:4], fgm, None, q)
            else:
                ml = ((acc - fgm) ** 2).mean()
            loss = loss + p.w_mask * note("mask", ml)
        if self.depth is not None and (p.w_depth > 0 or p.w_depth_grad > 0):
            loss = self._add_depth_loss(loss, f, out, fgm, note)
        if self.silhouette:
            wsil = p.w_silhouette * (1 - p.silhouette_decay * min(1.0, self.iteration / max(1, p.iterations)))
            loss = loss + wsil * note("silhouette", self.silhouette_loss(f, means_f))
        if targets is not None:
            loss = loss + p.w_track * note("track", self.track_loss(f, targets, feats, acc, q))
        return out, loss, psnr

    def _add_depth_loss(self, loss: torch.Tensor, f: int, out, fgm: torch.Tensor, note) -> torch.Tensor:
        """`loss` plus the disparity L1 and disparity-gradient terms (scene-scale free)."""
        p = self.p
        dmask = self.depth_valid[f][..., None]
        if not self.has_bg:
            dmask = dmask * (fgm > 0.5)
        pd = self.scale / (out.depth + 1e-5 * self.scale)
        td = self.scale / (self.depth[f][..., None] + 1e-5 * self.scale)
        td = torch.where(dmask > 0, td, torch.zeros_like(td))
        if p.w_depth > 0:
            loss = loss + p.w_depth * note("depth", masked_l1(pd, td, dmask, p.loss_quantile))
        if p.w_depth_grad > 0:
            loss = loss + p.w_depth_grad * note("depth_grad", gradient_loss(pd[None], td[None], dmask[None], 0.95))
        return loss

    def _regularisers(self, pick: torch.Tensor, note) -> torch.Tensor:
        """The once-per-step terms: smooth bases and tracks, speed, z velocity, scale variance, extra_loss."""
        p = self.p
        m = self.model
        T = self.data.num_timesteps
        reg = torch.zeros((), device=self.dev)
        if p.w_smooth_bases > 0 and T >= 3:
            reg = reg + p.w_smooth_bases * note(
                "smooth_bases", basis_smoothness(m.motion["rot6d"], m.motion["transl"], self.scale, p.smooth_bases)
            )
        if (p.w_smooth_tracks > 0 or p.w_z_accel > 0 or p.w_speed > 0 or p.w_isometry > 0) and T >= 3:
            ts = self.tidx[pick].clamp(1, T - 2)
            nb = torch.cat([ts - 1, ts, ts + 1])
            mn = m.fg_means_at(nb.to(self.dev)).reshape(m.num_fg, 3, len(ts), 3)
            if p.w_smooth_tracks > 0:
                a = (2 * mn[:, 1] - mn[:, 0] - mn[:, 2]).norm(dim=-1).mean() / self.scale
                reg = reg + p.w_smooth_tracks * 0.5 * note("smooth_tracks", a)
            if p.w_speed > 0:
                speed = (mn[:, 2] - mn[:, 1]).norm(dim=-1).mean() / self.scale
                reg = reg + p.w_speed * note("speed", speed)
            if p.w_isometry > 0:
                reg = reg + p.w_isometry * note("isometry", self._stretch(mn[:, 1], mn[:, 2]))
            if p.w_z_accel > 0:
                reg = reg + p.w_z_accel * note(
                    "z_vel", z_velocity_loss(mn, self.cam_centers[pick.to(self.dev)], self.scale)
                )
        if p.w_scale_var > 0:
            for g in m.parts().values():
                reg = reg + p.w_scale_var * last_dim_variance(g.get("log_scales")).mean()
        if self.extra_loss is not None:
            reg = reg + self.extra_loss(pick, note)
        return reg

    def _stretch(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Mean |d_ij(b) - d_ij(a)| / scale over each fg Gaussian i and its nearest canonical neighbours j."""
        nbrs = self._isometry_neighbours()
        if nbrs.shape[1] == 0:  # a single fg Gaussian has no neighbours: nothing to stretch
            return torch.zeros((), device=self.dev)
        da = pair_distances(a, nbrs, 1e-6 * self.scale)
        db = pair_distances(b, nbrs, 1e-6 * self.scale)
        return (db - da).abs().mean() / self.scale

    def _isometry_neighbours(self) -> torch.Tensor:
        """(N, k) indices of each fg Gaussian's nearest neighbours at its canonical position; rebuilt after
        density control changes the set."""
        m = self.model
        if self._nbrs is None or self._nbrs.shape[0] != m.num_fg:
            self._nbrs = nearest_neighbours(m.fg.get("means").detach(), self.p.isometry_neighbours).to(self.dev)
        return self._nbrs

    # -------------------------------------------------------------- density control
    def control(self) -> dict | None:
        p = self.p
        it = self.iteration
        stop = int(p.stop_control_fraction * p.iterations)
        if it <= p.warmup_steps or it % p.control_every != 0 or it >= stop:
            return None
        self.rules.use_screen = True
        every = p.reset_opacity_every
        self.rules.cull_by_size = every > 0 and it > every
        counts = control_step(self.model, self.optimizers, self.stats, self.rules, self.gen)
        self._nbrs = None
        if p.reset_opacity_every > 0 and it % p.reset_opacity_every == 0:
            self.reset_opacity()
        return counts

    @torch.no_grad()
    def reset_opacity(self) -> None:
        v = math.log(0.8 * self.p.cull_opacity_threshold / (1 - 0.8 * self.p.cull_opacity_threshold))
        for part, g in self.model.parts().items():
            prm = g.get("opacity_logits")
            prm.data.clamp_(max=v)
            st = self.optimizers[f"{part}.opacity_logits"].state.get(prm)
            if st:
                for k2 in ("exp_avg", "exp_avg_sq"):
                    st[k2].zero_()

    # -------------------------------------------------------------- evaluation
    @torch.no_grad()
    def psnr_all(self) -> float:
        self.use_level(1)
        vals = []
        for f in range(self.data.num_frames):
            out, _ = self.render_frame(f, with_mask=False)
            mse = float(((out.features[..., :3] - self.images[f]) ** 2).mean())
            vals.append(-10 * math.log10(max(mse, 1e-10)))
        return float(np.mean(vals))

    # -------------------------------------------------------------- checkpoint
    def checkpoint_state(self, digest: str) -> dict[str, Any]:
        return {
            "version": CHECKPOINT_VERSION,
            "digest": digest,
            "model": self.model.state(),
            "scene_scale": self.model.scene_scale,
            "optimizers": {k: v.state_dict() for k, v in self.optimizers.items()},
            "stats": self.stats.state(),
            "generator": self.gen.get_state(),
            "iteration": self.iteration,
            "curve": dict(self.curve.__dict__),
            "elapsed": self.elapsed,
            "canonical_frame": self.canonical_frame,
            "motion_source": self.motion_source,
            "init_info": self.init_info,
            "pending": {"loss": list(self._loss_acc), "psnr": list(self._psnr_acc)},
            "isometry_neighbours": None if self._nbrs is None else self._nbrs.cpu().clone(),
        }

    # -------------------------------------------------------------- loop
    def run(
        self,
        *,
        progress: bool = True,
        checkpoint: str | os.PathLike | None = None,
        digest: str = "",
        stop_at: int | None = None,
        stage: str = "recon",
    ) -> None:
        """Train to `stop_at` (default: the end). The log gets a progress line
        at a steady interval; `progress` adds a bar when stderr is a terminal."""
        p = self.p
        end = p.iterations if stop_at is None else min(stop_at, p.iterations)
        bar = Progress(stage, p.iterations, initial=self.iteration, bar=None if progress else False)
        t0 = time.perf_counter()
        base_elapsed = self.elapsed
        KERNELS.reset()
        try:
            while self.iteration < end:
                with self.clock.phase("step"):
                    loss, psnr = self.step()
                self._loss_acc.append(loss)
                self._psnr_acc.append(psnr)
                if self.iteration % p.log_every == 0 or self.iteration == p.iterations:
                    self.curve.iteration.append(self.iteration)
                    self.curve.loss.append(float(np.mean(self._loss_acc)))
                    self.curve.psnr.append(float(np.mean(self._psnr_acc)))
                    self.curve.num_gaussians.append(self.model.num_gaussians)
                    self._loss_acc, self._psnr_acc = [], []
                bar.update(self.iteration, loss=loss, psnr=psnr, gaussians=self.model.num_gaussians)
                self.elapsed = base_elapsed + time.perf_counter() - t0
                if (
                    checkpoint is not None
                    and (self.iteration % p.checkpoint_every == 0)
                    and self.iteration < p.iterations
                ):
                    save_checkpoint(checkpoint, self.checkpoint_state(digest))
        finally:
            bar.close()
            for name in ("raster_forward", "raster_backward", "kernel_build"):
                self.clock.add(name, KERNELS.total(name))

    def time_breakdown(self) -> dict[str, float]:
        """Seconds of this process's training steps by phase: the rasterizer's
        kernels (CPU backend; 0 on gsplat) and their one-time compilation, the rest of the rendering (poses,
        colours), the losses, the rest of the autograd backward, the optimiser,
        density control, and the remainder (Python, gap filling)."""
        c = self.clock
        raster_fwd, raster_bwd = c.total("raster_forward"), c.total("raster_backward")
        build = c.total("kernel_build")  # a fresh cache compiles the CPU kernel at the first render
        parts = {
            "rasterizer_forward": raster_fwd,
            "rasterizer_backward": raster_bwd,
            "kernel_build": build,
            "render_other": c.total("render") - raster_fwd - build,
            "autograd_other": c.total("backward") - raster_bwd,
            "optimizer": c.total("optimizer"),
            "density_control": c.total("density_control"),
        }
        steps = c.total("step")
        known = c.total("render") + c.total("backward") + c.total("optimizer") + c.total("density_control")
        parts["losses_and_other"] = steps - known
        parts["steps_total"] = steps
        return {k: round(max(v, 0.0), 3) for k, v in parts.items()}
