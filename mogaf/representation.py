"""The 4D Gaussian representation (Shape-of-Motion style) and its artefact schema.

Dynamic (foreground) Gaussians live in a canonical space and move with a
blend of B shared SE(3) motion bases (paper, "Preliminary", Eq. 4-5):
    T_g(t) = blend_b( w_gb , T_b(t) ),   w_g = softmax(motion_coef_logits_g)
    mu_g(t) = R_g(t) mu_g + t_g(t),      R_g(t)' = R_g(t) R_g
The blend is done, as in Shape-of-Motion, on the continuous-6D rotation and
translation of each basis, followed by Gram-Schmidt; background Gaussians
are static. Our 6D vector is a rotation's first two rows (Shape-of-Motion's:
its first two columns): the same rotations round trip, but a blend of
different bases Gram-Schmidts to a slightly different rotation (0.03 deg for
bases 0.1 rad apart).

recon.h5 / refined.h5 layout (stages "recon" and "refine"):
  fg/means (N,3)           canonical means
  fg/quats (N,4)           canonical rotations, wxyz
  fg/log_scales (N,3)      log of the per-axis standard deviations
  fg/opacity_logits (N,)   opacity = sigmoid(.)
  fg/color_logits (N,3)    colour = sigmoid(.) (SH degree 0 term)
  fg/sh_rest (N,M,3)       higher SH coefficients, only if sh_degree > 0
  fg/motion_coef_logits (N,B)
  bg/...                   the same minus motion, optional
  motion/rot6d (B,T,6)     bases at the observed time steps
  motion/translations (B,T,3)
  motion/timesteps (T,)    scene time-grid indices of the observed steps
  trajectories/means (N,T,3), trajectories/quats (N,T,4)
                           per-Gaussian poses at every observed step;
                           quaternions sign-continuous along time
  training/...             curves (iteration, loss, psnr) for reports
  groups/...               refined.h5 only: group_id (N,), group_rigid (K,),
                           group_static (K,)
attrs: sh_degree, num_bases, background (3 floats), scene_scale, wall_time_s
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .artefact import read_artefact, write_artefact
from .errors import input_error
from .sh import num_sh_rest

if TYPE_CHECKING:  # torch is imported where a function computes with it: reading a model needs only numpy
    import torch

MODEL_STAGES = ("recon", "refine")
GAUSSIAN_KEYS = ("means", "quats", "log_scales", "opacity_logits", "color_logits")


# ------------------------------------------------------------------ rotations
def normalize_quat(q: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """Unit quaternions; a zero quaternion maps to identity (finite gradient)."""
    import torch

    norm = q.norm(dim=-1, keepdim=True)
    identity = torch.zeros_like(q)
    identity[..., 0] = 1.0
    safe = torch.where(norm > eps, q / norm.clamp_min(eps), identity)
    return safe


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """wxyz quaternions (...,4) to rotation matrices (...,3,3)."""
    import torch

    w, x, y, z = normalize_quat(q).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Rotation matrices to wxyz quaternions with w >= 0 (rotmat_to_xyzw)."""
    import torch

    xyzw = rotmat_to_xyzw(R)
    q = torch.cat([xyzw[..., 3:], xyzw[..., :3]], dim=-1)
    return torch.where(q[..., :1] < 0, -q, q)


def matrix_to_quat_numpy(R: np.ndarray) -> np.ndarray:
    """matrix_to_quat of a NumPy array (float64), as a NumPy array."""
    import torch

    return matrix_to_quat(torch.from_numpy(np.ascontiguousarray(R, dtype=np.float64))).numpy()


def rotmat_to_xyzw(R: torch.Tensor) -> torch.Tensor:
    """Unit xyzw quaternions of rotation matrices (...,3,3), Markley's method
    (J. Guid. Control Dyn. 31(2), 2008): the four vectors 4 q_i q (his eq. 8,
    attitude matrix A = R^T) and the one with the largest 4 q_i^2
    normalised, which gives a unit quaternion for a slightly non-orthonormal
    matrix too. Every operation as roma.rotmat_to_unitquat's, so the same
    bits (tests/test_representation.py), but the largest diagonal entry is
    found with three comparisons: torch's argmax over a last dimension of 4
    is ten times as slow on the CPU."""
    import torch

    rows = R.transpose(-1, -2).unbind(-2)
    (a11, a12, a13), (a21, a22, a23), (a31, a32, a33) = (row.unbind(-1) for row in rows)
    # fmt: off
    x = torch.stack([1 + a11 - a22 - a33, a12 + a21, a13 + a31, a23 - a32,
                     a21 + a12, 1 + a22 - a33 - a11, a23 + a32, a31 - a13,
                     a31 + a13, a32 + a23, 1 + a33 - a11 - a22, a12 - a21,
                     a23 - a32, a31 - a13, a12 - a21, 1 + a11 + a22 + a33], dim=-1).unflatten(-1, (4, 4))
    # fmt: on
    i = first_argmax(x.diagonal(dim1=-2, dim2=-1))
    x_i = torch.gather(x, -2, i[..., None, None].expand(*i.shape, 1, 4))[..., 0, :]
    return x_i / torch.norm(x_i, dim=-1, keepdim=True)


def first_argmax(v: torch.Tensor) -> torch.Tensor:
    """torch.argmax(v, dim=-1) for a short last dimension: the first largest
    entry, a NaN counting as the largest (as argmax's), by one comparison per entry."""
    import torch

    best, index = v[..., 0], torch.zeros(v.shape[:-1], dtype=torch.long, device=v.device)
    for k in range(1, v.shape[-1]):
        entry = v[..., k]
        larger = (entry > best) | (entry.isnan() & ~best.isnan())
        best = torch.where(larger, entry, best)
        index = torch.where(larger, k, index)
    return index


def rot6d_to_matrix(x: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """Continuous 6D rotation (Zhou et al.) to matrices; rows b1, b2, b1 x b2."""
    import torch

    a1, a2 = x[..., :3], x[..., 3:6]
    b1 = a1 / a1.norm(dim=-1, keepdim=True).clamp_min(eps)
    a2p = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    b2 = a2p / a2p.norm(dim=-1, keepdim=True).clamp_min(eps)
    b3 = torch.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-2)


def matrix_to_rot6d(R: torch.Tensor) -> torch.Tensor:
    return R[..., :2, :].reshape(R.shape[:-2] + (6,))


def quat_sign_continuity(q: np.ndarray, axis: int = 1) -> np.ndarray:
    """Flip quaternions along `axis` so consecutive ones have dot >= 0."""
    q = np.array(q, dtype=np.float64, copy=True)
    qm = np.moveaxis(q, axis, 0)
    for t in range(1, qm.shape[0]):
        flip = np.sum(qm[t] * qm[t - 1], axis=-1) < 0
        qm[t][flip] *= -1
    return np.moveaxis(qm, 0, axis)


# ------------------------------------------------------------------ motion
def blend_bases(
    coefs: torch.Tensor, rot6d: torch.Tensor, translations: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Blend per-time bases: coefs (N,B), rot6d (B,...,6), translations (B,...,3).

    Returns R (N,...,3,3) and t (N,...,3).
    """
    import torch

    B = coefs.shape[1]
    r = torch.einsum("nb,bk->nk", coefs, rot6d.reshape(B, -1)).reshape((coefs.shape[0],) + rot6d.shape[1:])
    t = torch.einsum("nb,bk->nk", coefs, translations.reshape(B, -1)).reshape(
        (coefs.shape[0],) + translations.shape[1:]
    )
    return rot6d_to_matrix(r), t


# ------------------------------------------------------------------ containers
@dataclass
class GaussianSet:
    """Gaussian parameters as optimised (log-scales, logits)."""

    means: np.ndarray
    quats: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    color_logits: np.ndarray
    sh_rest: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def as_dict(self) -> dict[str, np.ndarray]:
        d = {k: getattr(self, k) for k in GAUSSIAN_KEYS}
        if self.sh_rest is not None:
            d["sh_rest"] = self.sh_rest
        return d

    def subset(self, index: np.ndarray) -> GaussianSet:
        return GaussianSet(**{k: (None if v is None else v[index]) for k, v in self.__dict__.items()})


@dataclass
class Model4D:
    fg: GaussianSet
    motion_coef_logits: np.ndarray  # (N, B)
    rot6d: np.ndarray  # (B, T, 6)
    translations: np.ndarray  # (B, T, 3)
    timesteps: np.ndarray  # (T,)
    trajectory_means: np.ndarray  # (N, T, 3)
    trajectory_quats: np.ndarray  # (N, T, 4)
    bg: GaussianSet | None = None
    sh_degree: int = 0
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    scene_scale: float = 1.0
    training: dict[str, np.ndarray] = field(default_factory=dict)
    groups: dict[str, np.ndarray] = field(default_factory=dict)
    attrs: dict[str, Any] = field(default_factory=dict)

    @property
    def num_bases(self) -> int:
        return int(self.rot6d.shape[0])

    def motion_coefs(self) -> np.ndarray:
        x = self.motion_coef_logits - self.motion_coef_logits.max(axis=1, keepdims=True)
        e = np.exp(x)
        return e / e.sum(axis=1, keepdims=True)


def _gaussians_from(tree: dict[str, Any], path: Path, prefix: str) -> GaussianSet:
    missing = [k for k in GAUSSIAN_KEYS if k not in tree]
    if missing:
        raise input_error(path, f"group '{prefix}' lacks {', '.join(missing)}")
    return GaussianSet(**{k: tree[k] for k in GAUSSIAN_KEYS}, sh_rest=tree.get("sh_rest"))


def save_model(
    path: str | os.PathLike, stage: str, model: Model4D, *, config_digest: str, attrs: dict[str, Any] | None = None
) -> Path:
    if stage not in MODEL_STAGES:
        raise ValueError(f"stage must be one of {MODEL_STAGES}")
    traj_q = quat_sign_continuity(model.trajectory_quats, axis=1).astype(np.float32)
    data: dict[str, Any] = {
        "fg": {**model.fg.as_dict(), "motion_coef_logits": model.motion_coef_logits},
        "motion": {"rot6d": model.rot6d, "translations": model.translations, "timesteps": model.timesteps},
        "trajectories": {"means": model.trajectory_means, "quats": traj_q},
    }
    if model.bg is not None:
        data["bg"] = model.bg.as_dict()
    if model.training:
        data["training"] = model.training
    if model.groups:
        data["groups"] = model.groups
    all_attrs = {
        **model.attrs,
        **(attrs or {}),
        "sh_degree": int(model.sh_degree),
        "num_bases": model.num_bases,
        "background": [float(c) for c in model.background],
        "scene_scale": float(model.scene_scale),
    }
    return write_artefact(path, stage, data, config_digest=config_digest, attrs=all_attrs)


def _check_sh_bands(path: Path, name: str, part: GaussianSet | None, sh_degree: int) -> None:
    """sh_rest must carry exactly the bands of the model's degree (renderers use what is stored)."""
    if part is None or len(part) == 0:
        return
    bands = 0 if part.sh_rest is None else int(np.asarray(part.sh_rest).shape[1])
    if bands != num_sh_rest(sh_degree):
        raise input_error(
            path,
            f"entry '{name}/sh_rest' holds {bands} SH coefficients per colour, "
            f"expected {num_sh_rest(sh_degree)} for sh_degree {sh_degree}",
        )


def load_model(path: str | os.PathLike, stages: tuple[str, ...] = MODEL_STAGES) -> Model4D:
    art = read_artefact(
        path, stages, required=["fg/means", "fg/motion_coef_logits", "motion/rot6d", "trajectories/means"]
    )
    p = Path(path)
    fg = _gaussians_from(art["fg"], p, "fg")
    N = len(fg)
    T = int(art["motion/timesteps"].shape[0])
    checks = {
        "trajectories/means": (N, T, 3),
        "trajectories/quats": (N, T, 4),
        "fg/motion_coef_logits": (N, art["motion/rot6d"].shape[0]),
    }
    for key, shape in checks.items():
        if tuple(art[key].shape) != shape:
            raise input_error(p, f"entry '{key}' has shape {tuple(art[key].shape)}, expected {shape}")
    sh_degree = int(art.attrs.get("sh_degree", 0))
    bg = _gaussians_from(art["bg"], p, "bg") if "bg" in art else None
    for name, part in (("fg", fg), ("bg", bg)):
        _check_sh_bands(p, name, part, sh_degree)
    known = {"sh_degree", "num_bases", "background", "scene_scale"}
    return Model4D(
        fg=fg,
        motion_coef_logits=art["fg/motion_coef_logits"],
        rot6d=art["motion/rot6d"],
        translations=art["motion/translations"],
        timesteps=np.asarray(art["motion/timesteps"], dtype=np.int64),
        trajectory_means=art["trajectories/means"],
        trajectory_quats=art["trajectories/quats"],
        bg=bg,
        sh_degree=sh_degree,
        background=tuple(art.attrs.get("background", (1.0, 1.0, 1.0))),
        scene_scale=float(art.attrs.get("scene_scale", 1.0)),
        training=art.get("training", {}) or {},
        groups=art.get("groups", {}) or {},
        attrs={k: v for k, v in art.attrs.items() if k not in known},
    )
