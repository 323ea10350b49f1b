"""The moving objects of the synthetic world and their surface sampling.

Each Object gives its ray-castable primitives, surface material points and
their world positions at motion time tau: rigid boxes and spheres
(RigidObject), the waving cloth, two-box chains (the bending arm and the
hinged-lid chest) and the soft blobs that merge (SoftBlob).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .motion import MergePath, rotation
from .primitives import Box, Ellipsoid, HeightCloth, Sphere


def _sample_box_surface(rng: np.random.Generator, half: np.ndarray, n: int) -> np.ndarray:
    """n points uniform on the surface of the box [-half, half] (local)."""
    areas = np.array(
        [
            half[1] * half[2],
            half[1] * half[2],
            half[0] * half[2],
            half[0] * half[2],
            half[0] * half[1],
            half[0] * half[1],
        ]
    )
    face = rng.choice(6, size=n, p=areas / areas.sum())
    pts = rng.uniform(-1.0, 1.0, (n, 3)) * half
    axis = face // 2
    sign = np.where(face % 2 == 1, 1.0, -1.0)
    pts[np.arange(n), axis] = sign * half[axis]
    return pts


def _sample_sphere_dirs(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _box_corners(half: np.ndarray) -> np.ndarray:
    s = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=np.float64)
    return s * half


class Object:
    inst: int
    name: str
    rigid: bool
    kind: str
    # The pieces that move each as one (ground truth for scoring a grouping
    # by part): one for most objects, one per box of a box chain.
    part_names: tuple[str, ...] = ("whole",)
    # instance ids of the objects this one may touch (bodies that meet: they stick or merge)
    touches: frozenset[int] = frozenset()

    def primitives(self, tau: float) -> list:
        raise NotImplementedError

    def sample_material(self, rng: np.random.Generator, n: int) -> np.ndarray:
        raise NotImplementedError

    def points(self, material: np.ndarray, tau: float) -> np.ndarray:
        raise NotImplementedError

    def extent_points(self, tau: float) -> np.ndarray:
        """Points whose projections bound the object's silhouette (view checks)."""
        raise NotImplementedError

    def point_parts(self, material: np.ndarray) -> np.ndarray:
        """(n,) index into part_names of each sampled material point."""
        return np.zeros(len(material), dtype=np.int64)

    def bounds(self, tau: float) -> list[tuple[np.ndarray, float]]:
        return [(p.centre, p.radius) for p in self.primitives(tau)]

    def shape(self) -> dict[str, Any]:
        """Geometry in the object's own frame (written to instances.json)."""
        return {}


class RigidObject(Object):
    rigid = True

    def __init__(self, inst, name, centre_fn, R0, spin_axis, spin_rate, spin_until: float = np.inf):
        self.inst, self.name = inst, name
        self.centre_fn, self.R0 = centre_fn, np.asarray(R0, dtype=np.float64)
        self.spin_axis, self.spin_rate = np.asarray(spin_axis, dtype=np.float64), float(spin_rate)
        # motion time from which the object spins no more (it holds that orientation)
        self.spin_until = float(spin_until)

    def rotation(self, tau: float) -> np.ndarray:
        return rotation(self.spin_axis, self.spin_rate * min(tau, self.spin_until)) @ self.R0

    def pose(self, tau: float) -> np.ndarray:
        """Object-to-world 4x4 transform at motion time tau."""
        T = np.eye(4)
        T[:3, :3] = self.rotation(tau)
        T[:3, 3] = self.centre_fn(tau)
        return T

    def points(self, material: np.ndarray, tau: float) -> np.ndarray:
        T = self.pose(tau)
        return material @ T[:3, :3].T + T[:3, 3]


class RigidBox(RigidObject):
    kind = "box"

    def __init__(self, inst, name, half, texture, **kw):
        super().__init__(inst, name, **kw)
        self.half, self.texture = np.asarray(half, dtype=np.float64), texture

    def primitives(self, tau):
        return [Box(self.rotation(tau), self.centre_fn(tau), self.half, self.texture, self.inst)]

    def sample_material(self, rng, n):
        return _sample_box_surface(rng, self.half, n)

    def extent_points(self, tau):
        return self.points(_box_corners(self.half), tau)

    def shape(self):
        return {"half_extents": self.half.tolist()}


class RigidSphere(RigidObject):
    kind = "sphere"

    def __init__(self, inst, name, radius, texture, **kw):
        super().__init__(inst, name, **kw)
        self.r, self.texture = float(radius), texture

    def primitives(self, tau):
        return [Sphere(self.rotation(tau), self.centre_fn(tau), self.r, self.texture, self.inst)]

    def sample_material(self, rng, n):
        return _sample_sphere_dirs(rng, n) * self.r

    def extent_points(self, tau):
        return self.centre_fn(tau) + _box_corners(np.full(3, self.r))

    def shape(self):
        return {"radius": self.r}


class SoftBlob(Object):
    """One of two soft balls that merge (motion.MergePath): spinning before the
    contact, then squashed along the line between them (volume kept), by the
    end of the merge shortened there by a share `squash` of its radius, and
    holding that shape."""

    rigid = False
    kind = "blob"

    def __init__(self, inst, name, radius, texture, path: MergePath, body: int, R0, spin_rate, squash: float):
        self.inst, self.name = inst, name
        self.r, self.texture = float(radius), texture
        self.path, self.body = path, int(body)
        self.R0, self.spin_rate, self.squash = np.asarray(R0, dtype=np.float64), float(spin_rate), float(squash)
        n = path.n
        # the roll each would have, rolling towards the other
        self.spin_axis = np.cross([0.0, 0.0, 1.0], n if body == 0 else -n)

    def shape(self):
        return {"radius": self.r, "squash": self.squash}

    def map(self, tau: float) -> np.ndarray:
        """A (3, 3): material direction u -> offset from the centre at tau."""
        angle = self.spin_rate * min(tau, self.path.tau_contact)
        R = rotation(self.spin_axis, angle) @ self.R0
        k = 1.0 - self.squash * self.path.merged(tau)  # along the line; 1 / sqrt(k) across keeps the volume
        n = self.path.n
        D = np.eye(3) / np.sqrt(k) + (k - 1.0 / np.sqrt(k)) * np.outer(n, n)
        return self.r * D @ R

    def primitives(self, tau):
        return [Ellipsoid(self.map(tau), self.path.centre(self.body, tau), self.texture, self.inst)]

    def sample_material(self, rng, n):
        return _sample_sphere_dirs(rng, n)

    def points(self, material, tau):
        return material @ self.map(tau).T + self.path.centre(self.body, tau)

    def extent_points(self, tau):
        half = np.linalg.norm(self.map(tau), axis=1)  # the ellipsoid's half-extent along each world axis
        return self.path.centre(self.body, tau) + _box_corners(half)


class Cloth(Object):
    """Flag pinned along a vertical edge (on a static pole), waving in a travelling wave."""

    rigid = False
    kind = "cloth"

    def __init__(self, inst, name, origin, yaw, length, height, amplitude, wavelength, frequency, texture):
        self.inst, self.name = inst, name
        self.origin = np.asarray(origin, dtype=np.float64)
        eu = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        ev = np.array([0.0, 0.0, 1.0])
        self.E = np.stack([eu, ev, np.cross(eu, ev)], axis=1)
        self.L, self.Hc, self.A = float(length), float(height), float(amplitude)
        self.k = 2.0 * np.pi / float(wavelength)
        self.omega = 2.0 * np.pi * float(frequency)
        self.q = 2.5  # wave fronts slightly slanted along the height
        self.texture = texture

    def shape(self):
        return {
            "length": self.L,
            "height": self.Hc,
            "amplitude": self.A,
            "pinned_edge_origin": self.origin.tolist(),
            "frame": self.E.tolist(),
        }

    def surface(self, tau: float) -> HeightCloth:
        return HeightCloth(
            self.origin, self.E, self.L, self.Hc, self.A, self.k, self.omega * tau, self.q, self.texture, self.inst
        )

    def primitives(self, tau):
        return [self.surface(tau)]

    def sample_material(self, rng, n):
        # keep clear of the pole that hides the pinned edge
        return np.stack([rng.uniform(0.04 * self.L, self.L, n), rng.uniform(0.0, self.Hc, n)], axis=1)

    def points(self, material, tau):
        return self.surface(tau).points(material[:, 0], material[:, 1])

    def extent_points(self, tau):
        u, v = np.meshgrid(np.linspace(0, self.L, 9), np.linspace(0, self.Hc, 5))
        pts = self.surface(tau).points(u.ravel(), v.ravel())
        n = self.E[:, 2]
        return np.concatenate([pts + self.A * n, pts - self.A * n])


class BoxChain(Object):
    """A non-rigid object made of two boxes, each moving rigidly:
    subclasses give segment_frames(tau) (rotation, centre per box) and halves()."""

    rigid = False

    def segment_frames(self, tau: float) -> list[tuple[np.ndarray, np.ndarray]]:
        raise NotImplementedError

    def halves(self) -> list[np.ndarray]:
        raise NotImplementedError

    def primitives(self, tau):
        return [
            Box(R, c, half, self.texture, self.inst, face_offset=3 * i, part=i)
            for i, ((R, c), half) in enumerate(zip(self.segment_frames(tau), self.halves()))
        ]

    def sample_material(self, rng, n):
        halves = self.halves()
        area = np.array([2 * (h[0] * h[1] + h[1] * h[2] + h[0] * h[2]) for h in halves])
        seg = rng.choice(2, size=n, p=area / area.sum())
        out = np.zeros((n, 4))
        out[:, 0] = seg
        for i, half in enumerate(halves):
            m = seg == i
            out[m, 1:] = _sample_box_surface(rng, half, int(m.sum()))
        return out

    def point_parts(self, material):
        return material[:, 0].astype(np.int64)

    def points(self, material, tau):
        frames = self.segment_frames(tau)
        out = np.zeros((len(material), 3))
        for i, (R, c) in enumerate(frames):
            m = material[:, 0] == i
            out[m] = material[m, 1:] @ R.T + c
        return out

    def extent_points(self, tau):
        return np.concatenate([_box_corners(h) @ R.T + c for (R, c), h in zip(self.segment_frames(tau), self.halves())])


class Arm(BoxChain):
    """Two-link arm standing on the ground, bending at shoulder and elbow, swaying about z."""

    kind = "arm"
    part_names = ("upper", "lower")

    def __init__(self, inst, name, base, lengths, thickness, texture, phase):
        self.inst, self.name = inst, name
        self.base = np.asarray(base, dtype=np.float64)
        self.lengths = [float(x) for x in lengths]
        self.thickness = float(thickness)
        self.texture, self.phase = texture, float(phase)

    def segment_frames(self, tau: float) -> list[tuple[np.ndarray, np.ndarray]]:
        yaw = 0.45 * np.sin(0.9 * tau + self.phase)
        th1 = 0.35 * np.sin(1.6 * tau + self.phase)
        th2 = 0.9 + 0.7 * np.sin(2.1 * tau + 0.6 + self.phase)
        Ryaw = rotation([0, 0, 1], yaw)
        R1 = Ryaw @ rotation([0, 1, 0], th1)
        R2 = R1 @ rotation([0, 1, 0], th2)
        c1 = self.base + R1 @ np.array([0, 0, self.lengths[0] / 2])
        elbow = self.base + R1 @ np.array([0, 0, self.lengths[0]])
        c2 = elbow + R2 @ np.array([0, 0, self.lengths[1] / 2])
        return [(R1, c1), (R2, c2)]

    def shape(self):
        return {"base": self.base.tolist(), "segment_lengths": self.lengths, "thickness": self.thickness}

    def halves(self) -> list[np.ndarray]:
        h = self.thickness / 2
        return [np.array([h, h, L / 2]) for L in self.lengths]


class Articulated(BoxChain):
    """A still body with one moving part: a box standing on the ground and a lid
    hinged along the top of its back edge, swinging open and shut. As one
    instance it is non-rigid; most of its surface (the body) never moves."""

    kind = "articulated"
    part_names = ("body", "lid")

    def __init__(self, inst, name, centre, body_half, lid_thickness, yaw, swing, rate, texture, phase):
        self.inst, self.name = inst, name
        self.centre = np.asarray(centre, dtype=np.float64)
        self.body_half = np.asarray(body_half, dtype=np.float64)
        self.lid_half = np.array([self.body_half[0], self.body_half[1], 0.5 * float(lid_thickness)])
        self.R = rotation([0, 0, 1], yaw)
        self.swing, self.rate, self.phase = float(swing), float(rate), float(phase)
        self.texture = texture

    def opening(self, tau: float) -> float:
        """Lid angle (radians) above closed: a swing between 0.15 and 0.15 + 2 swing."""
        return 0.15 + self.swing * (1.0 - np.cos(self.rate * tau + self.phase))

    def segment_frames(self, tau: float) -> list[tuple[np.ndarray, np.ndarray]]:
        bh, lh = self.body_half, self.lid_half
        hinge = self.centre + self.R @ np.array([0.0, bh[1], bh[2]])  # top of the back face
        Rl = self.R @ rotation([1, 0, 0], -self.opening(tau))  # negative about x: the front edge rises
        lid_centre = hinge + Rl @ np.array([0.0, -lh[1], lh[2]])
        return [(self.R, self.centre), (Rl, lid_centre)]

    def halves(self) -> list[np.ndarray]:
        return [self.body_half, self.lid_half]

    def shape(self):
        return {
            "centre": self.centre.tolist(),
            "body_half_extents": self.body_half.tolist(),
            "lid_half_extents": self.lid_half.tolist(),
        }
