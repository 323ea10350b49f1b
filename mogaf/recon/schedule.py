"""Per-iteration schedule of the reconstruction trainer (mixed into Trainer).

The base learning rate of every parameter tensor (_lr_names), its decay, the
time curriculum (which frames may be sampled at an iteration), the
extrapolation of the motion bases outside the curriculum window and the
cubic-spline fill of the steps without a training frame.
"""

from __future__ import annotations

import math

import torch


def _lr_names(params: dict, scale: float) -> dict[str, float]:
    s = scale if params.lr_scene_scaled else 1.0
    b = params.lr_boost
    lr = {
        "means": params.lr_means * s,
        "quats": params.lr_quats,
        "log_scales": params.lr_scales,
        "color_logits": params.lr_colors,
        "sh_rest": params.lr_colors / 20.0,
        "motion_coef_logits": params.lr_motion_coefs,
    }
    out = {}
    for part in ("fg", "bg"):
        for k, v in lr.items():
            out[f"{part}.{k}"] = v * b
        out[f"{part}.opacity_logits"] = getattr(params, f"lr_opacities_{part}") * b
    out["motion.rot6d"] = params.lr_rots * b
    out["motion.transl"] = params.lr_transls * s * b
    return out


class TrainerSchedule:
    """Learning rates, curriculum window and motion-basis gap filling of Trainer."""

    def set_lrs(self, it: int) -> None:
        frac = min(1.0, it / max(1, self.p.iterations))
        for name, opt in self.optimizers.items():
            lr = self.base_lr[name]
            if name.endswith("log_scales"):
                lr = lr * math.exp(math.log(0.1) * frac)  # SoM: x0.1 exponential decay
            for g in opt.param_groups:
                g["lr"] = lr

    def window(self, it: int) -> int:
        T = self.data.num_timesteps
        if not self.curriculum:
            return T
        n = max(1, int(self.p.curriculum_fraction * self.p.iterations))
        start = self.p.curriculum_start
        return int(min(T, start + (T - start) * it / n))

    def allowed_frames(self, it: int) -> torch.Tensor:
        if not self.curriculum:
            return torch.arange(self.data.num_frames)
        c = int(self.tidx[self.canonical_frame])
        w = self.window(it)
        ok = (self.tidx - c).abs() <= w
        return torch.nonzero(ok, as_tuple=False).squeeze(1)

    @torch.no_grad()
    def fill_gaps(self) -> None:
        """Steps without a training frame take the cubic-spline interpolation of the steps with one."""
        if self.gap_fill is None:
            return
        gaps, knots, M = self.gap_fill
        for key in ("rot6d", "transl"):
            x = self.model.motion[key].data
            x[:, gaps] = torch.einsum("gk,bkd->bgd", M, x[:, knots])

    @torch.no_grad()
    def extrapolate_bases(self, it: int) -> None:
        """Curriculum: steps outside the window follow the nearest in-window steps linearly."""
        if not self.curriculum:
            return
        T = self.data.num_timesteps
        c = int(self.tidx[self.canonical_frame])
        w = self.window(it)
        lo, hi = max(0, c - w), min(T - 1, c + w)
        for key in ("rot6d", "transl"):
            x = self.model.motion[key].data
            if hi < T - 1:
                v = x[:, hi] - x[:, hi - 1] if hi >= 1 and hi - 1 >= lo else torch.zeros_like(x[:, hi])
                k = torch.arange(1, T - hi, dtype=x.dtype, device=x.device).reshape(1, -1, 1)
                x[:, hi + 1 :] = x[:, hi : hi + 1] + k * v[:, None]
            if lo > 0:
                v = x[:, lo] - x[:, lo + 1] if lo + 1 <= hi else torch.zeros_like(x[:, lo])
                k = torch.arange(lo, 0, -1, dtype=x.dtype, device=x.device).reshape(1, -1, 1)
                x[:, :lo] = x[:, lo : lo + 1] + k * v[:, None]
