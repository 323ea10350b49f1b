"""Trainable 4D Gaussian model (torch) and its conversion to/from Model4D.

Parameters are kept as in mogaf.representation (log-scales, logits, wxyz
quaternions, continuous-6D basis rotations); every tensor is one named
parameter ("fg.means", "bg.color_logits", "motion.rot6d", ...) with its own
Adam optimiser, which keeps densification bookkeeping simple.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from ..representation import (
    GaussianSet,
    Model4D,
    blend_bases,
    matrix_to_quat,
    normalize_quat,
    quat_to_matrix,
)
from ..sh import gaussian_colors, num_sh_rest  # noqa: F401  (re-exported for the recon package)

GAUSS_FIELDS = ("means", "quats", "log_scales", "opacity_logits", "color_logits")

AUX_FIELDS = ("labels",)  # per-Gaussian tensors that are carried along but not optimised


class _SoftmaxOf(torch.autograd.Function):
    """softmax(logits) given its already computed value `probs`, with
    softmax's own backward: a step that reads the same softmax several times
    computes it once (a 10-wide last dimension is slow on the CPU), and each
    read keeps its own backward node, so the gradients are the same bits as
    with one torch.softmax per read."""

    @staticmethod
    def forward(ctx, logits: torch.Tensor, probs: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(probs)
        ctx.input_dtype = logits.dtype
        return probs.clone()

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        (probs,) = ctx.saved_tensors
        return torch._softmax_backward_data(grad, probs, -1, ctx.input_dtype), None


def last_dim_softmax(logits: torch.Tensor, cache: list) -> torch.Tensor:
    """torch.softmax(logits, -1), computed once while `logits` is unchanged:
    `cache` holds [tensor, its version, softmax] of the last call (an
    optimiser step or a replaced parameter starts a new one)."""
    if not cache or cache[0] is not logits or cache[1] != logits._version:
        with torch.no_grad():
            cache[:] = [logits, logits._version, torch.softmax(logits, dim=-1)]
    return _SoftmaxOf.apply(logits, cache[2])


class GaussianParams(nn.Module):
    def __init__(self, tensors: dict[str, torch.Tensor]):
        super().__init__()
        self.params = nn.ParameterDict(
            {k: nn.Parameter(v.detach().clone().float()) for k, v in tensors.items() if k not in AUX_FIELDS}
        )
        # aux: e.g. "labels" (N,) int64 instance id the Gaussian was initialised on (0 = unknown)
        self.aux: dict[str, torch.Tensor] = {k: v.detach().clone() for k, v in tensors.items() if k in AUX_FIELDS}
        self._coefs_cache: list = []  # last_dim_softmax's

    def __len__(self) -> int:
        return int(self.params["means"].shape[0])

    def get(self, name: str) -> torch.Tensor:
        return self.params[name]

    def scales(self) -> torch.Tensor:
        return torch.exp(self.params["log_scales"])

    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.params["opacity_logits"])

    def quats(self) -> torch.Tensor:
        return normalize_quat(self.params["quats"])

    def coefs(self) -> torch.Tensor:
        return last_dim_softmax(self.params["motion_coef_logits"], self._coefs_cache)

    def sh_rest(self) -> torch.Tensor | None:
        return self.params.get("sh_rest")

    def rows_aux(self, fn) -> None:
        """Apply a row operation (densify / cull) to the aux tensors."""
        self.aux = {k: fn(v) for k, v in self.aux.items()}

    def _apply(self, fn, recurse=True):  # keep aux on the module's device
        out = super()._apply(fn, recurse)
        self.aux = {k: fn(v) for k, v in self.aux.items()}
        return out

    def replace(self, name: str, value: torch.Tensor) -> nn.Parameter:
        p = nn.Parameter(value.detach().contiguous())
        self.params[name] = p
        return p

    def to_set(self) -> GaussianSet:
        d = {k: self.params[k].detach().cpu().numpy().astype(np.float32) for k in GAUSS_FIELDS}
        q = d["quats"]
        d["quats"] = (q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), 1e-12)).astype(np.float32)
        sh = self.sh_rest()
        return GaussianSet(**d, sh_rest=None if sh is None else sh.detach().cpu().numpy().astype(np.float32))


class ReconModel(nn.Module):
    """Dynamic fg Gaussians + B motion bases at T steps + optional static bg."""

    def __init__(
        self,
        fg: dict[str, torch.Tensor],
        rot6d: torch.Tensor,
        transl: torch.Tensor,
        bg: dict[str, torch.Tensor] | None = None,
        *,
        sh_degree: int = 0,
        scene_scale: float = 1.0,
    ):
        super().__init__()
        self.fg = GaussianParams(fg)
        self.bg = GaussianParams(bg) if bg is not None else None
        self.motion = nn.ParameterDict(
            {
                "rot6d": nn.Parameter(rot6d.detach().clone().float()),
                "transl": nn.Parameter(transl.detach().clone().float()),
            }
        )
        self.sh_degree = int(sh_degree)
        self.scene_scale = float(scene_scale)

    # -------------------------------------------------------------- sizes
    @property
    def num_fg(self) -> int:
        return len(self.fg)

    @property
    def num_bg(self) -> int:
        return 0 if self.bg is None else len(self.bg)

    @property
    def num_gaussians(self) -> int:
        return self.num_fg + self.num_bg

    @property
    def num_bases(self) -> int:
        return int(self.motion["rot6d"].shape[0])

    @property
    def num_timesteps(self) -> int:
        return int(self.motion["rot6d"].shape[1])

    def parts(self) -> dict[str, GaussianParams]:
        out = {"fg": self.fg}
        if self.bg is not None:
            out["bg"] = self.bg
        return out

    def named_tensors(self) -> dict[str, nn.Parameter]:
        """'fg.means', ..., 'motion.rot6d' -> parameter (stable order)."""
        out: dict[str, nn.Parameter] = {}
        for part, g in self.parts().items():
            for k, v in g.params.items():
                out[f"{part}.{k}"] = v
        for k, v in self.motion.items():
            out[f"motion.{k}"] = v
        return out

    # -------------------------------------------------------------- motion
    def fg_transforms(self, t: torch.Tensor, members: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """R (N,K,3,3), translation (N,K,3) of the fg Gaussians (all, or `members`) at step indices t (K,)."""
        coefs = (
            self.fg.coefs() if members is None else torch.softmax(self.fg.get("motion_coef_logits")[members], dim=-1)
        )
        return blend_bases(coefs, self.motion["rot6d"][:, t], self.motion["transl"][:, t])

    def fg_means_at(self, t: torch.Tensor, members: torch.Tensor | None = None) -> torch.Tensor:
        """Means (N,K,3) of the fg Gaussians (all, or `members`) at step indices t (K,)."""
        R, tr = self.fg_transforms(t, members)
        means = self.fg.get("means") if members is None else self.fg.get("means")[members]
        return torch.einsum("nkij,nj->nki", R, means) + tr

    def fg_poses_at(self, t: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Means (N,3) and wxyz quaternions (N,4) of the fg Gaussians at step index t."""
        R, tr = self.fg_transforms(torch.tensor([int(t)], device=self.motion["rot6d"].device))
        R, tr = R[:, 0], tr[:, 0]
        means = torch.einsum("nij,nj->ni", R, self.fg.get("means")) + tr
        quats = matrix_to_quat(R @ quat_to_matrix(self.fg.get("quats")))
        return means, quats

    # -------------------------------------------------------------- export
    @torch.no_grad()
    def trajectories(self, chunk: int = 16) -> tuple[np.ndarray, np.ndarray]:
        N, T = self.num_fg, self.num_timesteps
        means = np.zeros((N, T, 3), np.float32)
        quats = np.zeros((N, T, 4), np.float32)
        qc = quat_to_matrix(self.fg.get("quats"))
        for s in range(0, T, chunk):
            t = torch.arange(s, min(T, s + chunk), device=qc.device)
            R, tr = self.fg_transforms(t)
            means[:, s : s + len(t)] = (torch.einsum("nkij,nj->nki", R, self.fg.get("means")) + tr).cpu().numpy()
            quats[:, s : s + len(t)] = matrix_to_quat(R @ qc[:, None]).cpu().numpy()
        return means, quats

    def to_model4d(self, timesteps: np.ndarray, background: np.ndarray, training: dict | None = None) -> Model4D:
        tm, tq = self.trajectories()
        return Model4D(
            fg=self.fg.to_set(),
            motion_coef_logits=self.fg.get("motion_coef_logits").detach().cpu().numpy().astype(np.float32),
            rot6d=self.motion["rot6d"].detach().cpu().numpy().astype(np.float32),
            translations=self.motion["transl"].detach().cpu().numpy().astype(np.float32),
            timesteps=np.asarray(timesteps, dtype=np.int64),
            trajectory_means=tm,
            trajectory_quats=tq,
            bg=None if self.bg is None else self.bg.to_set(),
            sh_degree=self.sh_degree,
            background=tuple(float(c) for c in background),
            scene_scale=self.scene_scale,
            training=dict(training or {}),
        )

    # -------------------------------------------------------------- checkpoint
    def state(self) -> dict[str, torch.Tensor]:
        out = {k: v.detach().cpu().clone() for k, v in self.named_tensors().items()}
        for part, g in self.parts().items():
            for k, v in g.aux.items():
                out[f"{part}.{k}"] = v.detach().cpu().clone()
        return out

    @classmethod
    def from_state(cls, state: dict[str, torch.Tensor], *, sh_degree: int, scene_scale: float) -> ReconModel:
        fg = {k.split(".", 1)[1]: v for k, v in state.items() if k.startswith("fg.")}
        bg = {k.split(".", 1)[1]: v for k, v in state.items() if k.startswith("bg.")} or None
        return cls(fg, state["motion.rot6d"], state["motion.transl"], bg, sh_degree=sh_degree, scene_scale=scene_scale)
