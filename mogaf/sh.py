"""Real spherical-harmonics colours (degree <= 3), one convention for training and rendering.

A Gaussian's colour is sigmoid(colour logits + sum_m sh_rest_m Y_m(view dir)):
the degree-0 term is the colour logit itself and higher bands add a
view-dependent offset to it (Shape-of-Motion activates colours with a sigmoid).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # imported where a function computes with it: num_sh_rest needs no torch
    import torch

# Real spherical-harmonics constants (degree 0..3), as in 3DGS / gsplat.
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_rest(degree: int) -> int:
    return (degree + 1) ** 2 - 1


def sh_rest_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Real SH basis values of degree 1..`degree` for unit directions (N,3) -> (N,M)."""
    import torch

    x, y, z = dirs.unbind(-1)
    out = []
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * xz, SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4 * zz - xx - yy),
            SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            SH_C3[4] * x * (4 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3 * yy),
        ]
    return torch.stack(out, dim=-1)


def gaussian_colors(
    color_logits: torch.Tensor,
    sh_rest: torch.Tensor | None,
    means: torch.Tensor | None,
    cam_center: torch.Tensor | None,
) -> torch.Tensor:
    """Colour in [0, 1]: sigmoid(colour logits + sum_m sh_rest_m Y_m(view dir)).

    The degree-0 term is the colour logit itself (recon.h5 stores
    color_logits with colour = sigmoid(.)); higher degrees add a
    view-dependent offset to the logit.
    """
    import torch

    x = color_logits
    if sh_rest is not None and sh_rest.shape[1] > 0 and means is not None and cam_center is not None:
        degree = int(round(math.sqrt(sh_rest.shape[1] + 1))) - 1
        d = means - cam_center[None]
        d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        x = x + torch.einsum("nm,nmc->nc", sh_rest_basis(d, degree), sh_rest)
    return torch.sigmoid(x)
