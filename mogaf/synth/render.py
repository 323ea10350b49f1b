"""Ray-cast renderer: RGB (supersampled), depth and instance ids (pixel centres).

Primary rays go through sub-pixel sample positions (i + (k + 0.5) / ss) for
RGB and through pixel centres (i + 0.5, j + 0.5) for depth and instance ids,
following the convention of mogaf.camera. Ray directions have camera-space
z = 1, so the ray parameter is the camera-space depth.

Shading is Lambertian with one fixed directional light plus a strong ambient
term (no shadows, so the static background looks the same at every time).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LIGHT = np.array([-0.45, -0.7, 1.0]) / np.linalg.norm([-0.45, -0.7, 1.0])
AMBIENT = 0.6
DIFFUSE = 0.4


def camera_dirs(K: np.ndarray, H: int, W: int, ss: int = 1) -> np.ndarray:
    """Camera-space ray directions (H*ss, W*ss, 3) with z = 1 through sub-pixel centres."""
    offs = (np.arange(ss) + 0.5) / ss
    u = (np.arange(W)[:, None] + offs[None, :]).ravel()
    v = (np.arange(H)[:, None] + offs[None, :]).ravel()
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    y = (v - cy) / fy
    x = (u[None, :] - cx - skew * y[:, None]) / fx
    out = np.empty((len(v), len(u), 3))
    out[..., 0] = x
    out[..., 1] = y[:, None]
    out[..., 2] = 1.0
    return out


def camera_origin(w2c: np.ndarray) -> np.ndarray:
    return -w2c[:3, :3].T @ w2c[:3, 3]


def _rect(prim, K: np.ndarray, w2c: np.ndarray, ss: int, Hs: int, Ws: int):
    """Sub-pixel index rectangle (r0, r1, c0, c1) that can see `prim`, None if none."""
    if not np.isfinite(prim.radius):
        return 0, Hs, 0, Ws
    corners = prim.centre + prim.radius * np.array(
        [[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=np.float64
    )
    cam = corners @ w2c[:3, :3].T + w2c[:3, 3]
    if cam[:, 2].min() <= 1e-3:
        return 0, Hs, 0, Ws
    uv = cam @ K.T
    uv = uv[:, :2] / uv[:, 2:3] * ss
    c0 = max(int(np.floor(uv[:, 0].min())) - 1, 0)
    c1 = min(int(np.ceil(uv[:, 0].max())) + 1, Ws)
    r0 = max(int(np.floor(uv[:, 1].min())) - 1, 0)
    r1 = min(int(np.ceil(uv[:, 1].max())) + 1, Hs)
    if c0 >= c1 or r0 >= r1:
        return None
    return r0, r1, c0, c1


def cast_grid(o, dgrid, prims, K, w2c, ss, start=None, offset=0):
    """Nearest hit (t, index into prims + offset) for a grid of rays (Hs, Ws, 3)."""
    Hs, Ws = dgrid.shape[:2]
    if start is None:
        t = np.full((Hs, Ws), np.inf)
        idx = np.full((Hs, Ws), -1, dtype=np.int64)
    else:
        t, idx = start[0].copy(), start[1].copy()
    for k, prim in enumerate(prims):
        rect = _rect(prim, K, w2c, ss, Hs, Ws)
        if rect is None:
            continue
        r0, r1, c0, c1 = rect
        sub = dgrid[r0:r1, c0:c1]
        tk = prim.intersect(o, sub.reshape(-1, 3)).reshape(sub.shape[:2])
        closer = tk < t[r0:r1, c0:c1]
        t[r0:r1, c0:c1] = np.where(closer, tk, t[r0:r1, c0:c1])
        idx[r0:r1, c0:c1] = np.where(closer, k + offset, idx[r0:r1, c0:c1])
    return t, idx


def cast_rays(o: np.ndarray, d: np.ndarray, prims) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit (t, index into prims) for arbitrary rays d (N, 3) from origin o."""
    t = np.full(len(d), np.inf)
    idx = np.full(len(d), -1, dtype=np.int64)
    for k, prim in enumerate(prims):
        tk = prim.intersect(o, d)
        closer = tk < t
        t = np.where(closer, tk, t)
        idx = np.where(closer, k, idx)
    return t, idx


def shade(o, d, t, idx, prims, out=None, only_from: int = 0) -> np.ndarray:
    """Shaded colour (..., 3) of the hits; rays with idx < only_from keep `out`."""
    shape = t.shape
    d2, t2, i2 = d.reshape(-1, 3), t.ravel(), idx.ravel()
    col = np.zeros((len(t2), 3)) if out is None else out.reshape(-1, 3).copy()
    for k in np.unique(i2):
        if k < only_from:
            continue
        sel = np.nonzero(i2 == k)[0]
        dk = d2[sel]
        p = o + t2[sel, None] * dk
        albedo, n = prims[k].shade(p, dk)
        n = np.where((np.einsum("ij,ij->i", n, dk) > 0)[:, None], -n, n)
        lam = np.maximum(n @ LIGHT, 0.0)
        col[sel] = albedo * (AMBIENT + DIFFUSE * lam)[:, None]
    return col.reshape(shape + (3,))


@dataclass
class ViewResult:
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float64 camera-space z at pixel centres
    inst: np.ndarray  # (H, W) uint16 instance id at pixel centres
    part: np.ndarray  # (H, W) uint8 part index within that instance (0 on one-piece objects)


class Renderer:
    """Renders views of a World; caches the static background of fixed cameras."""

    def __init__(self, world):
        self.world = world
        p = world.params
        self.H, self.W, self.ss = p.height, p.width, p.supersample
        self.dirs_ss = camera_dirs(world.K, self.H, self.W, self.ss)
        self.dirs_c = camera_dirs(world.K, self.H, self.W, 1)
        self._static_cache: dict[int, tuple] = {}

    def _static(self, cam: int, w2c: np.ndarray):
        """(origin, world dirs ss, (t, idx) ss, colour ss, world dirs centre, (t, idx) centre)."""
        if cam != 0 and cam in self._static_cache:
            return self._static_cache[cam]
        world = self.world
        o = camera_origin(w2c)
        R = w2c[:3, :3]
        d_ss = self.dirs_ss @ R
        d_c = self.dirs_c @ R
        hit_ss = cast_grid(o, d_ss, world.static, world.K, w2c, self.ss)
        col = shade(o, d_ss, hit_ss[0], hit_ss[1], world.static)
        hit_c = cast_grid(o, d_c, world.static, world.K, w2c, 1)
        out = (o, d_ss, hit_ss, col, d_c, hit_c)
        if cam != 0:
            self._static_cache[cam] = out
        return out

    def cache_fixed_cameras(self) -> None:
        """Compute every fixed camera's static background now (before threads share the cache)."""
        for cam in range(1, self.world.num_cameras):
            self._static(cam, self.world.camera_w2c(cam, 0))

    def render(self, cam: int, ti: int) -> ViewResult:
        world = self.world
        w2c = world.camera_w2c(cam, ti)
        o, d_ss, hit_ss, col_static, d_c, hit_c = self._static(cam, w2c)
        n_static = len(world.static)
        prims = list(world.static) + world.dynamic_primitives(ti)
        dyn = prims[n_static:]
        t, idx = cast_grid(o, d_ss, dyn, world.K, w2c, self.ss, start=hit_ss, offset=n_static)
        col = shade(o, d_ss, t, idx, prims, out=col_static, only_from=n_static)
        ss = self.ss
        col = col.reshape(self.H, ss, self.W, ss, 3).mean(axis=(1, 3))
        rgb = np.clip(np.round(col * 255.0), 0, 255).astype(np.uint8)
        tc, ic = cast_grid(o, d_c, dyn, world.K, w2c, 1, start=hit_c, offset=n_static)
        if np.any(ic < 0):
            raise RuntimeError("synthetic renderer: a pixel ray missed the background")
        inst_of = np.array([pr.inst for pr in prims], dtype=np.uint16)
        part_of = np.array([pr.part for pr in prims], dtype=np.uint8)
        return ViewResult(rgb=rgb, depth=tc, inst=inst_of[ic], part=part_of[ic])

    def first_hit(self, cam: int, ti: int, points: np.ndarray):
        """Cast rays from camera `cam` at frame ti towards `points` (N, 3).

        Returns (uv (N, 2), z (N,) camera depth of the points, t (N,) depth of
        the first surface on the ray, inst (N,) its instance id).
        """
        world = self.world
        w2c = world.camera_w2c(cam, ti)
        o = camera_origin(w2c)
        cam_pts = points @ w2c[:3, :3].T + w2c[:3, 3]
        z = cam_pts[:, 2]
        zsafe = np.where(z > 1e-9, z, 1e-9)
        uv = (cam_pts @ world.K.T)[:, :2] / zsafe[:, None]
        d = (points - o) / zsafe[:, None]
        prims = list(world.static) + world.dynamic_primitives(ti)
        t, idx = cast_rays(o, d, prims)
        inst_of = np.array([pr.inst for pr in prims], dtype=np.int64)
        inst = np.where(idx >= 0, inst_of[np.maximum(idx, 0)], -1)
        return uv, z, t, inst
