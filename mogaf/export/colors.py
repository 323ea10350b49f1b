"""Colours in the 3DGS convention, from the model's (mogaf.sh).

3DGS viewers colour a Gaussian seen along unit direction d (from the camera
centre to its mean) as

    max(0.5 + SH_C0 * f_dc + sum_m f_rest_m Y_m(d), 0)

(linear in the SH coefficients), while the model's colour is
sigmoid(color_logits + sum_m sh_rest_m Y_m(d)) with the same real SH basis
Y_m (mogaf.sh.sh_rest_basis). At SH degree 0 the colour does not depend on d
and converts exactly: f_dc = (sigmoid(color_logits) - 0.5) / SH_C0. Above it
a sigmoid of a spherical polynomial is no spherical polynomial, so the
coefficients are its orthogonal projection onto the SH of the model's degree:
the 3DGS colour closest to the model's over all view directions (least
squares on the sphere), computed with a product Gauss-Legendre x uniform
quadrature.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.special import expit  # the logistic sigmoid, without overflow for large logits

from ..sh import SH_C0, num_sh_rest, sh_rest_basis

# Gaussians whose colours are fitted at once: bounds the (chunk, directions, 3)
# working arrays (about 100 MB in float64 at the default quadrature).
FIT_CHUNK = 4096


def sh_degree_of(num_rest: int) -> int:
    """The SH degree whose higher bands hold `num_rest` coefficients per colour."""
    degree = int(round(np.sqrt(num_rest + 1))) - 1
    if num_sh_rest(degree) != num_rest:
        raise ValueError(f"{num_rest} higher SH coefficients per colour fit no SH degree")
    return degree


def sphere_quadrature(order: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (Q, 3) and weights (Q,) summing to 4 pi: `order`
    Gauss-Legendre nodes in z = cos(theta) times 2 * `order` uniform azimuths,
    exact for spherical polynomials of degree below 2 * `order`."""
    z, wz = np.polynomial.legendre.leggauss(int(order))
    phi = (np.arange(2 * order) + 0.5) * (np.pi / order)
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    dirs = np.stack(
        [
            r[:, None] * np.cos(phi)[None],
            r[:, None] * np.sin(phi)[None],
            np.broadcast_to(z[:, None], (z.size, phi.size)),
        ],
        axis=-1,
    ).reshape(-1, 3)
    weights = np.broadcast_to(wz[:, None] * (np.pi / order), (z.size, phi.size)).reshape(-1)
    return dirs, np.ascontiguousarray(weights)


def splat_sh(
    color_logits: np.ndarray, sh_rest: np.ndarray | None, quadrature_order: int
) -> tuple[np.ndarray, np.ndarray]:
    """3DGS SH coefficients (f_dc (N, 3), f_rest (N, M, 3)), float64, of the
    model's colours: exact at degree 0, the least-squares fit over the
    sphere above (module docstring)."""
    logits = np.asarray(color_logits, np.float64)
    rest = np.zeros((logits.shape[0], 0, 3)) if sh_rest is None else np.asarray(sh_rest, np.float64)
    if rest.shape[1] == 0:
        return (expit(logits) - 0.5) / SH_C0, rest
    degree = sh_degree_of(rest.shape[1])
    dirs, weights = sphere_quadrature(quadrature_order)
    basis = sh_rest_basis(torch.from_numpy(dirs), degree).numpy()  # (Q, M)
    # the projection's basis: Y_0 = SH_C0 first, the weights folded in
    project = weights[:, None] * np.concatenate([np.full((dirs.shape[0], 1), SH_C0), basis], axis=1)  # (Q, 1 + M)
    coefs = np.empty((logits.shape[0], 1 + rest.shape[1], 3))
    for start in range(0, logits.shape[0], FIT_CHUNK):
        part = slice(start, start + FIT_CHUNK)
        colors = expit(logits[part, None, :] + np.matmul(basis, rest[part]))  # (n, Q, 3)
        coefs[part] = np.matmul(project.T, colors - 0.5)
    return coefs[:, 0], coefs[:, 1:]


def splat_colors(sh_dc: np.ndarray, sh_rest: np.ndarray, means: torch.Tensor, cam_center: torch.Tensor) -> torch.Tensor:
    """(N, 3) float32 colours as 3DGS viewers compute them from f_dc (N, 3) and
    f_rest (N, M, 3), for the camera centred at `cam_center`."""
    dc = torch.as_tensor(np.asarray(sh_dc), dtype=torch.float64)
    colors = 0.5 + SH_C0 * dc
    rest = torch.as_tensor(np.asarray(sh_rest), dtype=torch.float64)
    if rest.shape[1] > 0:
        d = means.to(torch.float64) - cam_center.to(torch.float64)[None]
        d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        colors = colors + torch.einsum("nm,nmc->nc", sh_rest_basis(d, sh_degree_of(rest.shape[1])), rest)
    return colors.clamp_min(0.0).to(torch.float32)
