"""Procedural, resolution-independent textures (albedo in [0, 1]).

All textures are smooth closed-form functions of surface coordinates: soft
checkers (tanh of a sine product, so edges are a few centimetres wide) and
"wave noise" (a seeded sum of plane waves). They have enough detail for
photometric reconstruction at 160x120 while staying band-limited, and can be
evaluated exactly at any ray hit.
"""

from __future__ import annotations

import numpy as np


def soft_checker(a: np.ndarray, b: np.ndarray, period: float, sharpness: float = 4.0) -> np.ndarray:
    """~0/1 checker of square size `period` with smooth edges."""
    s = np.sin(np.pi * a / period) * np.sin(np.pi * b / period)
    return 0.5 + 0.5 * np.tanh(sharpness * s)


class WaveNoise:
    """Sum of plane waves with seeded directions, wavelengths and phases; ~[-1, 1]."""

    def __init__(self, rng: np.random.Generator, n: int, min_wavelength: float, max_wavelength: float):
        angle = rng.uniform(0.0, 2.0 * np.pi, n)
        wavelength = np.exp(rng.uniform(np.log(min_wavelength), np.log(max_wavelength), n))
        k = 2.0 * np.pi / wavelength
        self.freq = np.stack([k * np.cos(angle), k * np.sin(angle)], axis=1)  # (n, 2)
        self.phase = rng.uniform(0.0, 2.0 * np.pi, n)
        amp = np.sqrt(wavelength)
        self.amp = amp / amp.sum() * 1.6

    def __call__(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        out = np.zeros(np.shape(a), dtype=np.float64)
        for (fa, fb), ph, am in zip(self.freq, self.phase, self.amp):
            out += am * np.sin(fa * a + fb * b + ph)
        return np.clip(out, -1.0, 1.0)


def mix(c0, c1, w: np.ndarray) -> np.ndarray:
    """Blend colours c0, c1 (3,) with weights w (N,) -> (N, 3)."""
    c0 = np.asarray(c0, dtype=np.float64)
    c1 = np.asarray(c1, dtype=np.float64)
    w = np.asarray(w, dtype=np.float64)[..., None]
    return c0 * (1.0 - w) + c1 * w


def hsv_to_rgb(h: float, s: float, v: float) -> np.ndarray:
    i = int(h * 6.0) % 6
    f = h * 6.0 - int(h * 6.0)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return np.array([(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i], dtype=np.float64)


class PlaneTexture:
    """Background texture: soft checker of two colours + wave-noise shading and tint."""

    def __init__(self, rng: np.random.Generator, c0, c1, period: float, tint):
        self.c0, self.c1, self.period = c0, c1, period
        self.tint = np.asarray(tint, dtype=np.float64)
        self.noise = WaveNoise(rng, 7, 0.12, 0.9)
        self.noise2 = WaveNoise(rng, 5, 0.3, 1.5)
        self.offset = rng.uniform(0.0, period, 2)

    def __call__(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        chk = soft_checker(a + self.offset[0], b + self.offset[1], self.period, 3.0)
        col = mix(self.c0, self.c1, chk)
        col = col * (1.0 + 0.28 * self.noise(a, b))[:, None]
        col = col + 0.12 * self.noise2(a, b)[:, None] * self.tint
        return np.clip(col, 0.0, 1.0)


class BoxTexture:
    """Per-face colours, a 3x3 soft checker per face and a corner mark (shows rotation)."""

    def __init__(self, rng: np.random.Generator, hue0: float):
        hues = (hue0 + np.arange(6) / 6.0 + rng.uniform(-0.03, 0.03, 6)) % 1.0
        self.face_colour = np.stack([hsv_to_rgb(h, 0.65, 0.85) for h in hues])  # (6, 3)
        self.noise = WaveNoise(rng, 5, 0.3, 1.2)

    def __call__(self, face: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """face in 0..5, (a, b) in [-1, 1] face coordinates."""
        base = self.face_colour[face]
        chk = soft_checker(a + 1.0, b + 1.0, 2.0 / 3.0, 3.0)
        col = base * (0.55 + 0.45 * chk)[:, None]
        # a light disc near one corner of every face makes the in-plane rotation visible
        mark = np.exp(-(((a - 0.55) ** 2 + (b - 0.55) ** 2) / 0.05))
        col = col * (1.0 - mark[:, None]) + 0.95 * mark[:, None]
        col = col * (1.0 + 0.12 * self.noise(a, b))[:, None]
        return np.clip(col, 0.0, 1.0)


class SphereTexture:
    """Longitude/latitude soft checker of two colours plus a polar cap."""

    def __init__(self, rng: np.random.Generator, hue: float):
        self.c0 = hsv_to_rgb(hue % 1.0, 0.75, 0.9)
        self.c1 = hsv_to_rgb((hue + 0.5) % 1.0, 0.35, 0.95)
        self.cap = hsv_to_rgb((hue + 0.25) % 1.0, 0.8, 0.5)
        self.sectors = 8

    def __call__(self, n_local: np.ndarray) -> np.ndarray:
        """n_local: (N, 3) unit vectors in the sphere's own frame."""
        lon = np.arctan2(n_local[:, 1], n_local[:, 0])
        lat = np.arcsin(np.clip(n_local[:, 2], -1.0, 1.0))
        s = np.sin(lon * self.sectors / 2.0) * np.sin(lat * 4.0 + 0.3)
        chk = 0.5 + 0.5 * np.tanh(3.0 * s)
        col = mix(self.c0, self.c1, chk)
        cap = 0.5 + 0.5 * np.tanh(12.0 * (n_local[:, 2] - 0.82))
        return mix(np.zeros(3), self.cap, cap) + col * (1.0 - cap[:, None])


class ClothTexture:
    """Flag: horizontal stripes, a checker canton near the pinned edge, fine noise."""

    def __init__(self, rng: np.random.Generator):
        self.c0 = np.array([0.85, 0.18, 0.15])
        self.c1 = np.array([0.95, 0.93, 0.85])
        self.c2 = np.array([0.12, 0.25, 0.65])
        self.noise = WaveNoise(rng, 5, 0.08, 0.4)

    def __call__(self, u: np.ndarray, v: np.ndarray, length: float, height: float) -> np.ndarray:
        stripes = 0.5 + 0.5 * np.tanh(3.0 * np.sin(2.0 * np.pi * v / (height / 3.5)))
        col = mix(self.c0, self.c1, stripes)
        canton = (0.5 + 0.5 * np.tanh(40.0 * (0.42 * length - u))) * (0.5 + 0.5 * np.tanh(40.0 * (v - 0.5 * height)))
        chk = soft_checker(u, v, 0.1, 3.0)
        canton_col = mix(self.c2, np.array([0.9, 0.85, 0.3]), chk * 0.8)
        col = col * (1.0 - canton[:, None]) + canton_col * canton[:, None]
        return np.clip(col * (1.0 + 0.1 * self.noise(u, v))[:, None], 0.0, 1.0)
