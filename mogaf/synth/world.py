"""The synthetic world: static background, moving objects and the cameras.

World frame: z up, ground plane z = 0, back wall y = WALL_Y, the cameras look
roughly along +y at LOOK_AT. Units are metres. Object motion is a function of
motion time tau = speed * t (see params.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import MogafError
from .primitives import Box, HeightCloth, Plane, Sphere
from .textures import BoxTexture, ClothTexture, PlaneTexture, SphereTexture

WALL_Y = 2.6
LOOK_AT = np.array([0.0, 1.05, 0.68])
TRAIN_OFFSET = np.array([0.0, -3.0, 0.55])  # mean train camera centre - LOOK_AT
UP = np.array([0.0, 0.0, 1.0])


def rotation(axis, angle) -> np.ndarray:
    """Rodrigues rotation matrix about `axis` by `angle` (radians)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * (K @ K)


def look_at(centre, target, roll: float = 0.0) -> np.ndarray:
    """OpenCV world-to-camera matrix of a camera at `centre` looking at `target` (z up)."""
    centre = np.asarray(centre, dtype=np.float64)
    f = np.asarray(target, dtype=np.float64) - centre
    f /= np.linalg.norm(f)
    r = np.cross(f, UP)
    r /= np.linalg.norm(r)
    dn = np.cross(f, r)
    R = np.stack([r, dn, f])
    if roll:
        R = rotation([0, 0, 1], roll) @ R
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ centre
    return T


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


def _clamped_velocity(v: np.ndarray, tau_max: float, max_travel: float) -> np.ndarray:
    travel = float(np.linalg.norm(v)) * tau_max
    return v * min(1.0, max_travel / travel) if travel > 0 else v


# ---------------------------------------------------------------- objects
class Object:
    inst: int
    name: str
    rigid: bool
    kind: str

    def primitives(self, tau: float) -> list:
        raise NotImplementedError

    def sample_material(self, rng: np.random.Generator, n: int) -> np.ndarray:
        raise NotImplementedError

    def points(self, material: np.ndarray, tau: float) -> np.ndarray:
        raise NotImplementedError

    def extent_points(self, tau: float) -> np.ndarray:
        """Points whose projections bound the object's silhouette (view checks)."""
        raise NotImplementedError

    def bounds(self, tau: float) -> list[tuple[np.ndarray, float]]:
        return [(p.centre, p.radius) for p in self.primitives(tau)]

    def shape(self) -> dict[str, Any]:
        """Geometry in the object's own frame (written to instances.json)."""
        return {}


class RigidObject(Object):
    rigid = True

    def __init__(self, inst, name, centre_fn, R0, spin_axis, spin_rate):
        self.inst, self.name = inst, name
        self.centre_fn, self.R0 = centre_fn, np.asarray(R0, dtype=np.float64)
        self.spin_axis, self.spin_rate = np.asarray(spin_axis, dtype=np.float64), float(spin_rate)

    def rotation(self, tau: float) -> np.ndarray:
        return rotation(self.spin_axis, self.spin_rate * tau) @ self.R0

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
            Box(R, c, half, self.texture, self.inst, face_offset=3 * i)
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


class Ballistic:
    """Centre of a sphere thrown at tau = 0: parabola under gravity, bouncing on the ground.

    Horizontal motion is uniform and centred on the sequence (the middle frame
    is at xy_mid); vertical motion starts at z0 with vz0 and loses a factor
    `restitution` of its speed at every bounce (where z = radius).
    """

    def __init__(self, xy_mid, v_xy, tau_mid, z0, vz0, gravity, restitution, radius, tau_max):
        self.xy_mid, self.v_xy, self.tau_mid = np.asarray(xy_mid, float), np.asarray(v_xy, float), float(tau_mid)
        self.g, self.floor = float(gravity), float(radius)
        # segments: (start tau, start z, start vz)
        segs = [(0.0, float(z0), float(vz0))]
        while True:
            t0, z, vz = segs[-1]
            land = t0 + (vz + np.sqrt(vz * vz + 2 * self.g * (z - self.floor))) / self.g
            if land > tau_max + 1.0:
                break
            v_after = -restitution * (vz - self.g * (land - t0))
            if v_after < 0.05 or len(segs) > 64:
                segs.append((land, self.floor, 0.0))
                break
            segs.append((land, self.floor, v_after))
        self.segments = segs
        self.bounces = [s[0] for s in segs[1:]]

    def __call__(self, tau: float) -> np.ndarray:
        t0, z, vz = [s for s in self.segments if s[0] <= tau][-1]
        dt = tau - t0
        if vz == 0.0 and z == self.floor and t0 > 0:
            zt = self.floor
        else:
            zt = z + vz * dt - 0.5 * self.g * dt * dt
        xy = self.xy_mid + self.v_xy * (tau - self.tau_mid)
        return np.array([xy[0], xy[1], max(zt, self.floor)])


def _linear(mid, v, tau_mid):
    mid, v = np.asarray(mid, float), np.asarray(v, float)
    return lambda tau: mid + v * (tau - tau_mid)


# Lanes for extra objects: nominal centre (they drift from there), chosen in order.
EXTRA_LANES = [
    (0.0, 2.2, 1.45),
    (-0.7, 0.45, 0.3),
    (-0.35, 0.6, 1.2),
    (-0.7, 2.1, 0.45),
    (0.95, 1.1, 0.3),
    (-0.1, 0.3, 0.75),
]


@dataclass
class World:
    params: dict[str, Any]
    objects: list[Object]
    static: list  # background primitives (instance 0)
    taus: np.ndarray  # (T,) motion time of every frame
    times: np.ndarray  # (T,) seconds
    train_w2c: np.ndarray  # (T, 4, 4)
    test_w2c: np.ndarray  # (2, 4, 4)
    K: np.ndarray  # (3, 3)
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def width(self) -> int:
        return int(self.params["width"])

    @property
    def height(self) -> int:
        return int(self.params["height"])

    def camera_w2c(self, cam: int, ti: int) -> np.ndarray:
        return self.train_w2c[ti] if cam == 0 else self.test_w2c[cam - 1]

    def dynamic_primitives(self, ti: int) -> list:
        tau = float(self.taus[ti])
        return [p for obj in self.objects for p in obj.primitives(tau)]


def _jitter(rng: np.random.Generator, t: np.ndarray, amplitude: float) -> np.ndarray:
    """Smooth handheld shake (T, 3): a few low-frequency sines per axis."""
    freqs = np.array([0.45, 1.1, 1.9])
    weights = np.array([1.0, 0.6, 0.35])
    phase = rng.uniform(0, 2 * np.pi, (3, 3))
    out = np.zeros((len(t), 3))
    for axis in range(3):
        for f, w, ph in zip(freqs, weights, phase[axis]):
            out[:, axis] += w * np.sin(2 * np.pi * f * t + ph)
    return amplitude * out / weights.sum()


def build_world(params: dict[str, Any]) -> World:
    """Objects, background and cameras for resolved `params` (see params.resolve_params)."""
    p = params
    rng = np.random.default_rng([int(p["seed"]), 20240611])
    T = p["num_frames"]
    times = np.arange(T) / p["fps"]
    taus = p["speed"] * times
    tau_max = float(taus[-1])
    tau_mid = 0.5 * tau_max
    spin = p["spin"]

    # ---- static background: ground, back wall and the flag pole
    ground_tex = PlaneTexture(rng, [0.78, 0.68, 0.52], [0.47, 0.52, 0.36], 0.42, [0.08, 0.0, -0.08])
    wall_tex = PlaneTexture(rng, [0.62, 0.68, 0.78], [0.86, 0.82, 0.70], 0.55, [-0.05, 0.02, 0.1])

    def pole_tex(face, a, b):
        return np.tile(np.array([0.35, 0.33, 0.32]), (len(face), 1)) * (0.85 + 0.15 * np.cos(6 * b))[:, None]

    static: list = [Plane(2, 0.0, (0, 1), ground_tex), Plane(1, WALL_Y, (0, 2), wall_tex)]

    objects: list[Object] = []
    # ---- textured box: uniform translation + constant spin (screw motion)
    v_box = _clamped_velocity(np.array(p["box_velocity"]), tau_max, p["max_travel"])
    rigid_objects: list[Object] = []
    rigid_objects.append(
        RigidBox(
            1,
            "box",
            half=[0.24, 0.18, 0.15],
            texture=BoxTexture(rng, rng.uniform()),
            centre_fn=_linear([-0.45, 1.4, 0.98], v_box, tau_mid),
            R0=rotation(rng.normal(size=3), rng.uniform(0, 2 * np.pi)),
            spin_axis=[0.35, 0.25, 1.0],
            spin_rate=p["box_spin"] * spin,
        )
    )
    # ---- sphere on a ballistic arc (bounces when the sequence is long/fast enough)
    r_s = 0.18
    v_xy = _clamped_velocity(np.array(p["sphere_velocity"]), tau_max, p["max_travel"])
    ballistic = Ballistic(
        [0.42, 0.75], v_xy, tau_mid, 0.42, p["sphere_launch_vz"], p["gravity"], p["restitution"], r_s, tau_max
    )
    vh = np.array([v_xy[0], v_xy[1], 0.0])
    roll_axis = np.cross(UP, vh) if np.linalg.norm(vh) > 1e-9 else np.array([1.0, 0.0, 0.0])
    rigid_objects.append(
        RigidSphere(
            2,
            "sphere",
            radius=r_s,
            texture=SphereTexture(rng, rng.uniform()),
            centre_fn=ballistic,
            R0=rotation(rng.normal(size=3), rng.uniform(0, 2 * np.pi)),
            spin_axis=roll_axis + np.array([0.0, 0.0, 0.3]) * np.linalg.norm(roll_axis),
            spin_rate=p["sphere_spin"] * spin,
        )
    )
    if p["rigid_objects"]:
        objects.extend(rigid_objects)
    # ---- non-rigid object
    if p["nonrigid"] == "articulated":
        objects.append(
            Articulated(
                3,
                "chest",
                centre=[0.0, 1.25, 0.3],
                body_half=[0.42, 0.28, 0.3],
                lid_thickness=0.06,
                yaw=np.deg2rad(-15.0),
                swing=p["lid_swing"],
                rate=p["lid_rate"],
                texture=BoxTexture(rng, rng.uniform()),
                phase=0.0,
            )
        )
    elif p["nonrigid"] == "cloth":
        pole_x, pole_y = 0.3, 1.85
        static.append(Box(np.eye(3), [pole_x, pole_y, 0.68], [0.025, 0.025, 0.68], pole_tex, 0))
        objects.append(
            Cloth(
                3,
                "cloth",
                origin=[pole_x, pole_y, 0.55],
                yaw=np.deg2rad(22.0),
                length=0.85,
                height=0.7,
                amplitude=p["cloth_amplitude"],
                wavelength=p["cloth_wavelength"],
                frequency=p["cloth_frequency"],
                texture=ClothTexture(rng),
            )
        )
    else:
        static.append(Box(np.eye(3), [0.7, 1.8, 0.05], [0.12, 0.12, 0.05], pole_tex, 0))  # plinth
        objects.append(
            Arm(
                3,
                "arm",
                base=[0.7, 1.8, 0.1],
                lengths=[0.6, 0.5],
                thickness=0.13,
                texture=BoxTexture(rng, rng.uniform()),
                phase=rng.uniform(0, 2 * np.pi),
            )
        )

    # ---- cameras
    W, H = p["width"], p["height"]
    f = 0.5 * W / np.tan(np.deg2rad(p["hfov_deg"]) / 2)
    K = np.array([[f, 0.0, W / 2], [0.0, f, H / 2], [0.0, 0.0, 1.0]])
    u = times / times[-1]
    walk = np.stack(
        [p["camera_sweep"] * (u - 0.5), 0.15 * np.sin(np.pi * u) - 0.05, 0.02 * np.sin(2 * np.pi * u)], axis=1
    )
    centres = LOOK_AT + TRAIN_OFFSET + walk + _jitter(rng, times, p["camera_jitter"])
    targets = LOOK_AT + _jitter(rng, times, 2.5 * p["camera_jitter"])
    rolls = 0.01 * np.sin(2 * np.pi * 0.6 * times + rng.uniform(0, 2 * np.pi))
    train_w2c = np.stack([look_at(c, tg, r) for c, tg, r in zip(centres, targets, rolls)])
    test = []
    for yaw_deg, dist, dz, roll in zip(p["test_camera_yaw_deg"], (1.0, 1.05), (-0.12, 0.2), (0.015, -0.02)):
        off = rotation(UP, np.deg2rad(yaw_deg)) @ (TRAIN_OFFSET * np.array([dist, dist, 1.0]))
        test.append(look_at(LOOK_AT + off + np.array([0, 0, dz]), LOOK_AT + np.array([0.0, 0.0, -0.03]), roll))
    test_w2c = np.stack(test)

    world = World(
        params=p, objects=objects, static=static, taus=taus, times=times, train_w2c=train_w2c, test_w2c=test_w2c, K=K
    )
    world.info["sphere_bounce_times"] = [float(b / p["speed"]) for b in ballistic.bounces if b <= tau_max]
    problem = check_world(world)
    if problem:
        raise MogafError(f"synthetic scene: {problem}; lower speed/max_travel or num_frames")

    # ---- extra small rigid objects, rejection-sampled so they stay in view and apart
    for i in range(p["num_extra_objects"]):
        lane = np.array(EXTRA_LANES[i])
        for _attempt in range(200):
            kind = "box" if (i + _attempt) % 2 == 0 else "sphere"
            size = rng.uniform(0.07, 0.11)
            a = rng.uniform(0, 2 * np.pi)
            v = p["extra_speed"] * np.array([np.cos(a), 0.35 * rng.uniform(-1, 1), 0.6 * np.sin(a)])
            v = _clamped_velocity(v, tau_max, min(p["max_travel"], 0.6))
            kw = dict(  # noqa: C408 (keyword names read as the parameters they are)
                centre_fn=_linear(lane + rng.uniform(-0.08, 0.08, 3), v, tau_mid),
                R0=rotation(rng.normal(size=3), rng.uniform(0, 2 * np.pi)),
                spin_axis=rng.normal(size=3),
                spin_rate=rng.uniform(1.0, 2.5) * spin,
            )
            inst = 4 + i
            if kind == "box":
                half = size * np.array([1.0, rng.uniform(0.6, 1.0), rng.uniform(0.6, 1.0)])
                obj: Object = RigidBox(
                    inst, f"box_extra_{i + 1}", half=half, texture=BoxTexture(rng, rng.uniform()), **kw
                )
            else:
                obj = RigidSphere(
                    inst, f"sphere_extra_{i + 1}", radius=size, texture=SphereTexture(rng, rng.uniform()), **kw
                )
            world.objects.append(obj)
            if check_world(world) is None:
                break
            world.objects.pop()
        else:
            raise MogafError(f"synthetic scene: could not place extra object {i + 1} in view without collisions")
    return world


def check_world(world: World, margin_px: float = 1.0) -> str | None:
    """Why the world is unusable (object out of a view, colliding, in the background), or None."""
    W, H = world.width, world.height
    objs = world.objects
    static_boxes = [prim for prim in world.static if isinstance(prim, Box)]
    for ti, tau in enumerate(world.taus):
        tau = float(tau)
        ext = {o.inst: o.extent_points(tau) for o in objs}
        for o in objs:
            pts = ext[o.inst]
            if pts[:, 2].min() < -1e-6:
                return f"{o.name} goes below the ground at frame {ti}"
            if pts[:, 1].max() > WALL_Y - 0.02:
                return f"{o.name} reaches the back wall at frame {ti}"
            for cam in (0, 1, 2):
                w2c = world.camera_w2c(cam, ti)
                cam_pts = pts @ w2c[:3, :3].T + w2c[:3, 3]
                if cam_pts[:, 2].min() < 0.3:
                    return f"{o.name} is behind or too close to camera {cam} at frame {ti}"
                uv = cam_pts @ world.K.T
                uv = uv[:, :2] / uv[:, 2:3]
                if uv.min() < margin_px or uv[:, 0].max() > W - margin_px or uv[:, 1].max() > H - margin_px:
                    return f"{o.name} leaves the view of camera {cam} at frame {ti}"
        bounds = {o.inst: o.bounds(tau) for o in objs}
        for i, a in enumerate(objs):
            for b in objs[i + 1 :]:
                for ca, ra in bounds[a.inst]:
                    for cb, rb in bounds[b.inst]:
                        if np.linalg.norm(ca - cb) < ra + rb + 0.03:
                            return f"{a.name} and {b.name} may collide at frame {ti}"
        for a in objs:
            if a.kind in ("cloth", "arm"):
                continue  # pinned on the pole / standing on the plinth
            for ca, ra in bounds[a.inst]:
                for box in static_boxes:
                    gap = np.maximum(np.abs((ca - box.c) @ box.R) - box.half, 0.0)
                    if np.linalg.norm(gap) < ra + 0.03:
                        return f"{a.name} may hit the pole at frame {ti}"
    return None
