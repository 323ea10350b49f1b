"""Analytic ray casting of the synthetic scene's primitives (vectorised numpy).

Rays are `o + t d` with one origin `o` (3,) and directions `d` (N, 3). The
renderer scales directions so their camera-space z component is 1, which
makes the ray parameter t equal to the camera-space depth of the hit.

Every primitive has an instance id (0 = static background), a part index
within its object (0 but for the boxes of a box chain), a bounding sphere, `intersect(o, d) -> t` (inf where missed) and
`shade(p, d) -> (albedo, normal)` at hit points p.
"""

from __future__ import annotations

import numpy as np

EPS = 1e-6


def _safe(d: np.ndarray) -> np.ndarray:
    return np.where(np.abs(d) < 1e-300, 1e-300, d)


def bound_hit(o: np.ndarray, d: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """Rays (N,) whose line passes within `radius` of `centre` in front of the origin."""
    oc = centre - o
    dd = np.einsum("ij,ij->i", d, d)
    proj = d @ oc
    dist2 = oc @ oc - proj * proj / dd
    far = proj + radius * np.sqrt(dd)  # positive if part of the sphere is ahead
    return (dist2 <= radius * radius) & (far > 0)


def first_sphere_hit(oc: np.ndarray, d: np.ndarray, r2: float) -> np.ndarray:
    """Ray parameter t of the first hit of rays `oc + t d` (origin relative to
    the centre, directions (N, 3)) with the sphere of squared radius r2 about
    the origin; inf where missed or behind."""
    a = np.einsum("ij,ij->i", d, d)
    b = d @ oc
    cc = oc @ oc - r2
    disc = b * b - a * cc
    with np.errstate(invalid="ignore"):
        t = (-b - np.sqrt(disc)) / a
    return np.where((disc >= 0) & (t > EPS), t, np.inf)


class Plane:
    """Infinite plane {x : x[axis] = offset}, textured with the two other coordinates."""

    part = 0

    def __init__(self, axis: int, offset: float, coords: tuple[int, int], texture, inst: int = 0):
        self.axis, self.offset, self.coords, self.texture, self.inst = axis, float(offset), coords, texture, inst
        self.centre, self.radius = None, np.inf

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        da = d[:, self.axis]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self.offset - o[self.axis]) / da
        return np.where(np.isfinite(t) & (t > EPS), t, np.inf)

    def shade(self, p: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        albedo = self.texture(p[:, self.coords[0]], p[:, self.coords[1]])
        normal = np.zeros_like(p)
        normal[:, self.axis] = 1.0
        return albedo, normal


class Box:
    """Oriented box: world = R @ local + c, local in [-half, half]."""

    def __init__(
        self, R: np.ndarray, c: np.ndarray, half: np.ndarray, texture, inst: int, face_offset: int = 0, part: int = 0
    ):
        self.part = part
        self.R = np.asarray(R, dtype=np.float64)
        self.c = np.asarray(c, dtype=np.float64)
        self.half = np.asarray(half, dtype=np.float64)
        self.texture, self.inst, self.face_offset = texture, inst, face_offset
        self.centre, self.radius = self.c, float(np.linalg.norm(self.half))

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        ol = (o - self.c) @ self.R
        inv = 1.0 / _safe(d @ self.R)
        t1 = (-self.half - ol) * inv
        t2 = (self.half - ol) * inv
        tmin = np.minimum(t1, t2).max(axis=1)
        tmax = np.maximum(t1, t2).min(axis=1)
        hit = (tmax >= tmin) & (tmin > EPS)
        return np.where(hit, tmin, np.inf)

    def shade(self, p: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = ((p - self.c) @ self.R) / self.half
        axis = np.argmax(np.abs(q), axis=1)
        rows = np.arange(len(q))
        sign = np.where(q[rows, axis] >= 0, 1.0, -1.0)
        face = 2 * axis + (sign > 0)
        a = q[rows, (axis + 1) % 3]
        b = q[rows, (axis + 2) % 3]
        albedo = self.texture((face + self.face_offset) % 6, np.clip(a, -1, 1), np.clip(b, -1, 1))
        normal = self.R[:, axis].T * sign[:, None]
        return albedo, normal


class Sphere:
    """Sphere of `radius` at `c`; R (local -> world) orients its texture."""

    part = 0

    def __init__(self, R: np.ndarray, c: np.ndarray, radius: float, texture, inst: int):
        self.R = np.asarray(R, dtype=np.float64)
        self.c = np.asarray(c, dtype=np.float64)
        self.r = float(radius)
        self.texture, self.inst = texture, inst
        self.centre, self.radius = self.c, self.r

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        return first_sphere_hit(o - self.c, d, self.r * self.r)

    def shade(self, p: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = (p - self.c) / self.r
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        return self.texture(n @ self.R), n


class HeightCloth:
    """Sheet pinned along its edge u = 0 with a travelling wave.

    Local frame E = [e_u, e_v, e_n] (columns) at `origin`; material point
    (u, v) in [0, L] x [0, Hc] sits at origin + u e_u + v e_v + h(u, v) e_n with
    h = A (u / L) sin(k u - phase + q v). Rays are intersected by bracketing
    between the planes n = -A and n = +A, sampling, then bisection.
    """

    SAMPLES = 16
    BISECTIONS = 16
    part = 0

    def __init__(self, origin, E, length, height, amplitude, k, phase, q, texture, inst):
        self.origin = np.asarray(origin, dtype=np.float64)
        self.E = np.asarray(E, dtype=np.float64)
        self.L, self.Hc, self.A, self.k, self.phase, self.q = (
            float(x) for x in (length, height, amplitude, k, phase, q)
        )
        self.texture, self.inst = texture, inst
        self.centre = self.origin + self.E @ np.array([self.L / 2, self.Hc / 2, 0.0])
        self.radius = float(np.sqrt((self.L / 2) ** 2 + (self.Hc / 2) ** 2 + self.A**2)) + 1e-3

    def height(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        uc = np.clip(u, 0.0, self.L)
        return self.A * (uc / self.L) * np.sin(self.k * uc - self.phase + self.q * v)

    def gradient(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        arg = self.k * u - self.phase + self.q * v
        s, c = np.sin(arg), np.cos(arg)
        hu = self.A / self.L * (s + u * self.k * c)
        hv = self.A * (u / self.L) * self.q * c
        return hu, hv

    def points(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        local = np.stack([u, v, self.height(u, v)], axis=-1)
        return self.origin + local @ self.E.T

    def _inside(self, u, v, margin=0.0):
        return (u >= -margin) & (u <= self.L + margin) & (v >= -margin) & (v <= self.Hc + margin)

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        t_out = np.full(len(d), np.inf)
        cand = np.nonzero(bound_hit(o, d, self.centre, self.radius))[0]
        if cand.size == 0:
            return t_out
        ol = (o - self.origin) @ self.E
        dl = d[cand] @ self.E
        dn = dl[:, 2]
        ok = np.abs(dn) > 1e-9
        dn = np.where(ok, dn, 1.0)
        sa = (-self.A - ol[2]) / dn
        sb = (self.A - ol[2]) / dn
        s_lo = np.maximum(np.minimum(sa, sb), EPS)
        s_hi = np.maximum(sa, sb)
        ok &= s_hi > s_lo
        frac = np.linspace(0.0, 1.0, self.SAMPLES)
        s = s_lo[:, None] + (s_hi - s_lo)[:, None] * frac[None, :]  # (n, S)

        def f(s_):
            u = ol[0] + s_ * dl[:, 0:1] if s_.ndim == 2 else ol[0] + s_ * dl[:, 0]
            v = ol[1] + s_ * dl[:, 1:2] if s_.ndim == 2 else ol[1] + s_ * dl[:, 1]
            n = ol[2] + s_ * dl[:, 2:3] if s_.ndim == 2 else ol[2] + s_ * dl[:, 2]
            return n - self.height(u, v), u, v

        fs, us, vs = f(s)
        change = np.signbit(fs[:, :-1]) != np.signbit(fs[:, 1:])
        mu = 0.5 * (us[:, :-1] + us[:, 1:])
        mv = 0.5 * (vs[:, :-1] + vs[:, 1:])
        margin = 0.02 * max(self.L, self.Hc)
        valid = change & self._inside(mu, mv, margin)
        has = valid.any(axis=1) & ok
        j = np.argmax(valid, axis=1)
        rows = np.arange(len(cand))
        a = s[rows, j]
        b = s[rows, j + 1]
        fa = fs[rows, j]
        for _ in range(self.BISECTIONS):
            m = 0.5 * (a + b)
            fm, _, _ = f(m)
            left = np.signbit(fm) != np.signbit(fa)
            b = np.where(left, m, b)
            a = np.where(left, a, m)
            fa = np.where(left, fa, fm)
        fb, _, _ = f(b)
        with np.errstate(divide="ignore", invalid="ignore"):
            root = np.where(np.abs(fb - fa) > 0, a - fa * (b - a) / (fb - fa), 0.5 * (a + b))
        root = np.clip(root, np.minimum(a, b), np.maximum(a, b))
        _, u, v = f(root)
        has &= self._inside(u, v)
        t_out[cand] = np.where(has, root, np.inf)
        return t_out

    def shade(self, p: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        local = (p - self.origin) @ self.E
        u, v = local[:, 0], local[:, 1]
        hu, hv = self.gradient(u, v)
        nl = np.stack([-hu, -hv, np.ones_like(hu)], axis=1)
        nl /= np.linalg.norm(nl, axis=1, keepdims=True)
        return self.texture(u, v, self.L, self.Hc), nl @ self.E.T


class Ellipsoid:
    """Ellipsoid {c + A u : |u| = 1} of an invertible map A (3, 3); u, the
    point's direction on the unit sphere, is its material coordinate, which
    the texture reads (so the pattern stretches with the surface)."""

    part = 0

    def __init__(self, A: np.ndarray, c: np.ndarray, texture, inst: int):
        self.A = np.asarray(A, dtype=np.float64)
        self.A_inv = np.linalg.inv(self.A)
        self.c = np.asarray(c, dtype=np.float64)
        self.texture, self.inst = texture, inst
        self.centre, self.radius = self.c, float(np.linalg.norm(self.A, 2))

    def intersect(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        # the unit sphere in u coordinates; t is the same ray parameter there
        return first_sphere_hit(self.A_inv @ (o - self.c), d @ self.A_inv.T, 1.0)

    def shade(self, p: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = (p - self.c) @ self.A_inv.T
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        n = u @ self.A_inv  # the gradient of |A^-1 (x - c)|^2: A^-T u
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        return self.texture(u), n
