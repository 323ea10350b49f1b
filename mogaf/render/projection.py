"""EWA projection of 3D Gaussians to the image plane, in differentiable torch.

Conventions follow gsplat's `fully_fused_projection` (pinhole, classic mode):

- world-to-camera `viewmat` (OpenCV: x right, y down, z forward), intrinsics K
  in pixels (fx = K[0,0], fy = K[1,1], cx = K[0,2], cy = K[1,2]; skew is
  ignored, as in gsplat); pixel (i, j) has its centre at (i + 0.5, j + 0.5);
- covariance R S S^T R^T from a wxyz quaternion (normalised here; a zero
  quaternion is the identity rotation with a zero, finite gradient) and linear
  scales; camera covariance W R S S^T R^T W^T;
- perspective Jacobian with x/z, y/z clamped to 1.3x the field of view (3DGS);
- `eps2d` (0.3 px^2) added to the 2D covariance (low-pass dilation);
- culled (radii = 0): z < near or z > far, non-finite, opacity < 1/255, or the
  box entirely off-screen;
- radii: per axis, ceil(extent * sqrt(Sigma2d_xx)) and ceil(extent * sqrt(Sigma2d_yy))
  with the opacity-aware extent min(3.33, sqrt(2 ln(255 o))) of gsplat; for
  o <= 1 the box contains every pixel where alpha >= 1/255, so the rendered image
  is exactly "all pairs with alpha >= 1/255", independent of tiles.

K is treated as a constant (no gradient), as in gsplat.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

ALPHA_MIN = 1.0 / 255.0
EXTENT_MAX = 3.33
RADIUS_MAX = float(2**30)


@dataclass
class Projected:
    """All per-Gaussian quantities, for all N Gaussians (culled ones are finite)."""

    means2d: torch.Tensor  # (N, 2) differentiable; zero for culled Gaussians
    conics: torch.Tensor  # (N, 3) inverse 2D covariance (a, b, c), differentiable
    depths: torch.Tensor  # (N,) camera-space z, differentiable (not clamped)
    radii: torch.Tensor  # (N, 2) int32, zero when culled
    visible: torch.Tensor  # (N,) bool


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """(N, 4) wxyz quaternions (any norm) to (N, 3, 3) rotations.

    A quaternion with squared norm <= 1e-24 maps to the identity; its gradient is
    exactly zero (the double-`where` keeps 0/0 out of the backward pass).
    """
    n2 = (quats * quats).sum(-1, keepdim=True)
    ok = n2 > 1e-24
    ident = torch.zeros_like(quats)
    ident[:, 0] = 1.0
    q = torch.where(ok, quats, ident)
    q = q * torch.rsqrt(torch.where(ok, n2, torch.ones_like(n2)))
    w, x, y, z = q.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    rows = [
        1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
        2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
        2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
    ]  # fmt: skip
    return torch.stack(rows, -1).reshape(-1, 3, 3)


def opacity_extent(opacities: torch.Tensor) -> torch.Tensor:
    """gsplat's opacity-aware box extent in sigmas (0 where o < 1/255)."""
    o = opacities.detach()
    ratio = torch.clamp(o / ALPHA_MIN, min=1.0)
    ext = torch.sqrt(2.0 * torch.log(ratio))
    ext = torch.clamp(ext, max=EXTENT_MAX)
    return torch.where(o >= ALPHA_MIN, ext, torch.zeros_like(ext))


def project_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
) -> Projected:
    dtype = means.dtype
    viewmat = viewmat.to(dtype)
    Kd = [float(v) for v in K.detach().to(torch.float64).reshape(-1).tolist()]
    fx, cx, fy, cy = Kd[0], Kd[2], Kd[4], Kd[5]

    Rw = viewmat[:3, :3]
    tw = viewmat[:3, 3]
    pc = means @ Rw.T + tw
    x, y, z = pc.unbind(-1)
    zd = z.detach()
    in_range = (zd >= near) & (zd <= far)
    z_s = torch.where(in_range, z, torch.ones_like(z))

    # Camera-space R S (columns are the scaled principal axes): cov_c = A A^T.
    R = quat_to_rotmat(quats)
    A = Rw @ (R * scales[:, None, :])

    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + 0.3 * tan_fovx
    lim_x_neg = cx / fx + 0.3 * tan_fovx
    lim_y_pos = (height - cy) / fy + 0.3 * tan_fovy
    lim_y_neg = cy / fy + 0.3 * tan_fovy
    rz = 1.0 / z_s
    rz2 = rz * rz
    tx = z_s * torch.clamp(x * rz, -lim_x_neg, lim_x_pos)
    ty = z_s * torch.clamp(y * rz, -lim_y_neg, lim_y_pos)
    # Rows of J A (2 x 3): J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]].
    u = (fx * rz)[:, None] * A[:, 0, :] - (fx * tx * rz2)[:, None] * A[:, 2, :]
    v = (fy * rz)[:, None] * A[:, 1, :] - (fy * ty * rz2)[:, None] * A[:, 2, :]
    uu = (u * u).sum(-1)
    vv = (v * v).sum(-1)
    uv = (u * v).sum(-1)
    sxx = uu + eps2d
    syy = vv + eps2d
    sxy = uv
    # det(J Sigma J^T) = |u x v|^2 (Lagrange identity): exact and >= 0, no cancellation.
    cr = torch.linalg.cross(u, v, dim=-1)
    det = (cr * cr).sum(-1) + eps2d * (uu + vv) + eps2d * eps2d
    mx = fx * x * rz + cx
    my = fy * y * rz + cy

    with torch.no_grad():
        ext = opacity_extent(opacities.reshape(-1)).to(dtype)
        rx = torch.ceil(ext * torch.sqrt(sxx.detach()))
        ry = torch.ceil(ext * torch.sqrt(syy.detach()))
        finite = (
            torch.isfinite(mx.detach()) & torch.isfinite(my.detach())
            & torch.isfinite(sxx.detach()) & torch.isfinite(syy.detach())
            & torch.isfinite(sxy.detach()) & torch.isfinite(det.detach()) & (det.detach() > 0)
        )  # fmt: skip
        rx = torch.where(finite, rx, torch.zeros_like(rx)).clamp(0.0, RADIUS_MAX)
        ry = torch.where(finite, ry, torch.zeros_like(ry)).clamp(0.0, RADIUS_MAX)
        mxd, myd = mx.detach(), my.detach()
        onscreen = (mxd + rx > 0) & (mxd - rx < width) & (myd + ry > 0) & (myd - ry < height)
        visible = in_range & finite & ((rx > 0) | (ry > 0)) & onscreen
        radii = torch.stack([rx, ry], -1).to(torch.int32) * visible[:, None].to(torch.int32)

    vis_f = visible[:, None]
    det_s = torch.where(visible, det, torch.ones_like(det))
    conics = torch.stack([syy / det_s, -sxy / det_s, sxx / det_s], -1)
    conics = torch.where(vis_f, conics, torch.zeros_like(conics))
    means2d = torch.stack([mx, my], -1)
    means2d = torch.where(vis_f, means2d, torch.zeros_like(means2d))
    return Projected(means2d=means2d, conics=conics, depths=z, radii=radii, visible=visible)
