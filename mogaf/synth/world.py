"""The synthetic world: static background, moving objects and the cameras.

World frame: z up, ground plane z = 0, back wall y = WALL_Y, the cameras look
roughly along +y at LOOK_AT. Units are metres. Object motion is a function of
motion time tau = speed * t (see params.py). The object classes live in
objects.py, their motions in motion.py; this module assembles the scene.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import MogafError
from .motion import Ballistic, MergePath, StuckPath, _clamped_velocity, _linear, rotation
from .objects import Arm, Articulated, Cloth, Object, RigidBox, RigidSphere, SoftBlob
from .params import TEST_CAMERA_PLACES, SyntheticSettings, load_settings
from .primitives import Box, Plane
from .textures import BoxTexture, ClothTexture, PlaneTexture, SphereTexture

WALL_Y = 2.6
LOOK_AT = np.array([0.0, 1.05, 0.68])
TRAIN_OFFSET = np.array([0.0, -3.0, 0.55])  # mean train camera centre - LOOK_AT
UP = np.array([0.0, 0.0, 1.0])


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


# Two spheres that collide and stick (params.stick_time): where their centres
# meet the contact point, the direction from the thrown sphere to the second
# one, the distances each travels to the contact and the second one's radius.
STICK_CONTACT = np.array([0.35, 0.95, 0.72])
STICK_DIRECTION = np.array([1.0, 0.2, 0.1]) / np.linalg.norm([1.0, 0.2, 0.1])
STICK_APPROACH = (0.45, 0.3)
STICK_RADIUS = 0.13
# the second body's instance id: the first after the box, the sphere and the
# non-rigid object (1-3); extra objects are numbered after it
SECOND_BODY_INST = 4


def _head_on(first_radius: float, tau_contact: float) -> tuple[tuple[float, float], np.ndarray, np.ndarray]:
    """The radii of two bodies that meet at motion time tau_contact and their
    velocities before it: head-on along STICK_DIRECTION, each covering its
    STICK_APPROACH distance by then."""
    n = STICK_DIRECTION
    return (first_radius, STICK_RADIUS), n * STICK_APPROACH[0] / tau_contact, -n * STICK_APPROACH[1] / tau_contact


def _stuck_partner(sphere: RigidSphere, texture, R0, tau_contact: float, spin_rate: float) -> RigidSphere:
    """The second, smaller sphere of a stuck pair; `sphere` is set on a head-on
    course with it (its path and spin change). They meet at motion time
    tau_contact and from then on move as one body with their common
    (momentum-weighted) velocity, spinning no more."""
    n = STICK_DIRECTION
    radii, v_a, v_b = _head_on(sphere.r, tau_contact)
    mass = np.array(radii) ** 3
    v_after = (mass[0] * v_a + mass[1] * v_b) / mass.sum()
    sphere.centre_fn = StuckPath(STICK_CONTACT - radii[0] * n, v_a, v_after, tau_contact)
    sphere.spin_axis, sphere.spin_rate, sphere.spin_until = np.cross(UP, n), spin_rate, tau_contact
    second = RigidSphere(
        SECOND_BODY_INST,
        "sphere_2",
        radius=radii[1],
        texture=texture,
        centre_fn=StuckPath(STICK_CONTACT + radii[1] * n, v_b, v_after, tau_contact),
        R0=R0,
        spin_axis=np.cross(UP, -n),
        spin_rate=spin_rate,
        spin_until=tau_contact,
    )
    return second


# Two soft blobs that merge (params.stick_bodies "blobs"): how much nearer
# their centres come after the contact (a share of the contact distance) and
# how much each is squashed along the line between them by then.
MERGE_OVERLAP = 0.45
MERGE_SQUASH = 0.25


def _merging_blobs(sphere: RigidSphere, texture, R0, tau_contact: float, spin_rate: float) -> list[SoftBlob]:
    """Two soft blobs in the place of the sphere and the second sphere of a
    stuck pair (the same course, radii, textures): they meet at tau_contact
    and merge (motion.MergePath, objects.SoftBlob)."""
    n = STICK_DIRECTION
    radii, v_a, v_b = _head_on(sphere.r, tau_contact)
    path = MergePath(
        STICK_CONTACT - radii[0] * n,
        STICK_CONTACT + radii[1] * n,
        v_a,
        v_b,
        np.array(radii) ** 3,
        tau_contact,
        MERGE_OVERLAP,
    )
    first = SoftBlob(sphere.inst, "blob", radii[0], sphere.texture, path, 0, sphere.R0, spin_rate, MERGE_SQUASH)
    second = SoftBlob(SECOND_BODY_INST, "blob_2", radii[1], texture, path, 1, R0, spin_rate, MERGE_SQUASH)
    return [first, second]


def _bodies_that_meet(p: SyntheticSettings, sphere: RigidSphere, rng, tau_contact: float, spin_rate: float) -> list:
    """The sphere and a second body meeting it at tau_contact (params.stick_time):
    a stuck pair of spheres or two merging blobs (params.stick_bodies), each
    allowed to touch the other (Object.touches)."""
    if not p.rigid_objects:
        raise MogafError("synthetic param 'stick_time' needs rigid_objects: the stuck pair's first body is the sphere")
    if p.stick_time >= p.motion_stop:
        raise MogafError(
            f"synthetic param 'stick_time' ({p.stick_time}) must come before motion_stop ({p.motion_stop}): "
            "the pair would stop before it meets"
        )
    # The second body's draws come after the box's and the sphere's, which so
    # draw as without it; a scene without the pair draws exactly as before.
    texture = SphereTexture(rng, rng.uniform())
    R0 = rotation(rng.normal(size=3), rng.uniform(0, 2 * np.pi))
    if p.stick_bodies == "blobs":
        first, second = _merging_blobs(sphere, texture, R0, tau_contact, spin_rate)
    else:
        first, second = sphere, _stuck_partner(sphere, texture, R0, tau_contact, spin_rate)
    first.touches, second.touches = frozenset({second.inst}), frozenset({first.inst})
    return [first, second]


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
    params: SyntheticSettings
    objects: list[Object]
    static: list  # background primitives (instance 0)
    taus: np.ndarray  # (T,) motion time of every frame
    times: np.ndarray  # (T,) seconds
    train_w2c: np.ndarray  # (T, 4, 4)
    test_w2c: np.ndarray  # (C, 4, 4), C = 1..3 held-out cameras
    K: np.ndarray  # (3, 3)
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def num_cameras(self) -> int:
        """The training camera (0) and the held-out cameras (1..)."""
        return 1 + len(self.test_w2c)

    @property
    def width(self) -> int:
        return int(self.params.width)

    @property
    def height(self) -> int:
        return int(self.params.height)

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


def build_world(params: dict[str, Any] | SyntheticSettings) -> World:
    """Objects, background and cameras for `params` (a mapping, see params.resolve_params, or SyntheticSettings)."""
    p = load_settings(params)
    rng = np.random.default_rng([int(p.seed), 20240611])
    T = p.num_frames
    times = np.arange(T) / p.fps
    # Velocities are sized for the whole sequence (tau_max); with motion_stop < 1
    # every object follows the same path and holds its pose from the stop on.
    tau_max = float(p.speed * times[-1])
    taus = p.speed * np.minimum(times, p.motion_stop * times[-1])
    tau_mid = 0.5 * tau_max
    spin = p.spin

    # ---- static background: ground, back wall and the flag pole
    ground_tex = PlaneTexture(rng, [0.78, 0.68, 0.52], [0.47, 0.52, 0.36], 0.42, [0.08, 0.0, -0.08])
    wall_tex = PlaneTexture(rng, [0.62, 0.68, 0.78], [0.86, 0.82, 0.70], 0.55, [-0.05, 0.02, 0.1])

    def pole_tex(face, a, b):
        return np.tile(np.array([0.35, 0.33, 0.32]), (len(face), 1)) * (0.85 + 0.15 * np.cos(6 * b))[:, None]

    static: list = [Plane(2, 0.0, (0, 1), ground_tex), Plane(1, WALL_Y, (0, 2), wall_tex)]

    objects: list[Object] = []
    # ---- textured box: uniform translation + constant spin (screw motion)
    v_box = _clamped_velocity(np.array(p.box_velocity), tau_max, p.max_travel)
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
            spin_rate=p.box_spin * spin,
        )
    )
    # ---- sphere on a ballistic arc (bounces when the sequence is long/fast enough)
    r_s = 0.18
    v_xy = _clamped_velocity(np.array(p.sphere_velocity), tau_max, p.max_travel)
    ballistic = Ballistic([0.42, 0.75], v_xy, tau_mid, 0.42, p.sphere_launch_vz, p.gravity, p.restitution, r_s, tau_max)
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
            spin_rate=p.sphere_spin * spin,
        )
    )
    stick = p.stick_time > 0
    if p.stick_bodies != "spheres" and not stick:
        raise MogafError(f"synthetic param 'stick_bodies' ({p.stick_bodies}) needs a stick_time above 0")
    if stick:
        tau_contact = p.stick_time * tau_max
        rigid_objects[1:] = _bodies_that_meet(p, rigid_objects[1], rng, tau_contact, p.sphere_spin * spin)
    if p.rigid_objects:
        objects.extend(rigid_objects)
    # ---- non-rigid object
    if p.nonrigid == "articulated":
        objects.append(
            Articulated(
                3,
                "chest",
                centre=[0.0, 1.25, 0.3],
                body_half=[0.42, 0.28, 0.3],
                lid_thickness=0.06,
                yaw=np.deg2rad(-15.0),
                swing=p.lid_swing,
                rate=p.lid_rate,
                texture=BoxTexture(rng, rng.uniform()),
                phase=0.0,
            )
        )
    elif p.nonrigid == "cloth":
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
                amplitude=p.cloth_amplitude,
                wavelength=p.cloth_wavelength,
                frequency=p.cloth_frequency,
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
    W, H = p.width, p.height
    f = 0.5 * W / np.tan(np.deg2rad(p.hfov_deg) / 2)
    K = np.array([[f, 0.0, W / 2], [0.0, f, H / 2], [0.0, 0.0, 1.0]])
    u = times / times[-1]
    walk = np.stack([p.camera_sweep * (u - 0.5), 0.15 * np.sin(np.pi * u) - 0.05, 0.02 * np.sin(2 * np.pi * u)], axis=1)
    centres = LOOK_AT + TRAIN_OFFSET + walk + _jitter(rng, times, p.camera_jitter)
    targets = LOOK_AT + _jitter(rng, times, 2.5 * p.camera_jitter)
    rolls = 0.01 * np.sin(2 * np.pi * 0.6 * times + rng.uniform(0, 2 * np.pi))
    train_w2c = np.stack([look_at(c, tg, r) for c, tg, r in zip(centres, targets, rolls)])
    test = []
    for yaw_deg, (dist, dz, roll) in zip(p.test_camera_yaw_deg, TEST_CAMERA_PLACES, strict=False):
        off = rotation(UP, np.deg2rad(yaw_deg)) @ (TRAIN_OFFSET * np.array([dist, dist, 1.0]))
        test.append(look_at(LOOK_AT + off + np.array([0, 0, dz]), LOOK_AT + np.array([0.0, 0.0, -0.03]), roll))
    test_w2c = np.stack(test)

    world = World(
        params=p, objects=objects, static=static, taus=taus, times=times, train_w2c=train_w2c, test_w2c=test_w2c, K=K
    )
    # the first body of a pair that meets is not thrown: it bounces nowhere
    bounces = [] if stick else [float(b / p.speed) for b in ballistic.bounces if b <= taus[-1]]
    world.info["sphere_bounce_times"] = bounces
    if stick:
        world.info["stick_time"] = float(tau_contact / p.speed)
    problem = check_world(world)
    if problem:
        # a pair's paths depend on stick_time alone (the contact is fixed, the approach spans stick_time)
        fix = (
            "raise stick_time"
            if stick and any(name in problem for name in ("sphere", "blob"))
            else "lower speed/max_travel or num_frames"
        )
        raise MogafError(f"synthetic scene: {problem}; {fix}")

    # ---- extra small rigid objects, rejection-sampled so they stay in view and apart
    first_extra = SECOND_BODY_INST + 1 if stick else SECOND_BODY_INST
    for i in range(p.num_extra_objects):
        lane = np.array(EXTRA_LANES[i])
        for _attempt in range(200):
            kind = "box" if (i + _attempt) % 2 == 0 else "sphere"
            size = rng.uniform(0.07, 0.11)
            a = rng.uniform(0, 2 * np.pi)
            v = p.extra_speed * np.array([np.cos(a), 0.35 * rng.uniform(-1, 1), 0.6 * np.sin(a)])
            v = _clamped_velocity(v, tau_max, min(p.max_travel, 0.6))
            kw = dict(  # noqa: C408 (keyword names read as the parameters they are)
                centre_fn=_linear(lane + rng.uniform(-0.08, 0.08, 3), v, tau_mid),
                R0=rotation(rng.normal(size=3), rng.uniform(0, 2 * np.pi)),
                spin_axis=rng.normal(size=3),
                spin_rate=rng.uniform(1.0, 2.5) * spin,
            )
            inst = first_extra + i
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


def _view_problem(world: World, o: Object, pts: np.ndarray, ti: int, margin_px: float) -> str | None:
    """Why the object's extent points at frame `ti` leave the room or a camera's view, or None."""
    W, H = world.width, world.height
    if pts[:, 2].min() < -1e-6:
        return f"{o.name} goes below the ground at frame {ti}"
    if pts[:, 1].max() > WALL_Y - 0.02:
        return f"{o.name} reaches the back wall at frame {ti}"
    for cam in range(world.num_cameras):
        w2c = world.camera_w2c(cam, ti)
        cam_pts = pts @ w2c[:3, :3].T + w2c[:3, 3]
        if cam_pts[:, 2].min() < 0.3:
            return f"{o.name} is behind or too close to camera {cam} at frame {ti}"
        uv = cam_pts @ world.K.T
        uv = uv[:, :2] / uv[:, 2:3]
        if uv.min() < margin_px or uv[:, 0].max() > W - margin_px or uv[:, 1].max() > H - margin_px:
            return f"{o.name} leaves the view of camera {cam} at frame {ti}"
    return None


def _collision_problem(objs: list[Object], bounds: dict[int, list], ti: int) -> str | None:
    """Which two objects' bounding spheres come close at frame `ti`, or None."""
    for i, a in enumerate(objs):
        for b in objs[i + 1 :]:
            if b.inst in a.touches:
                continue
            for ca, ra in bounds[a.inst]:
                for cb, rb in bounds[b.inst]:
                    if np.linalg.norm(ca - cb) < ra + rb + 0.03:
                        return f"{a.name} and {b.name} may collide at frame {ti}"
    return None


def _pole_problem(objs: list[Object], bounds: dict[int, list], static_boxes: list[Box], ti: int) -> str | None:
    """Which free object comes close to a static box (the pole) at frame `ti`, or None."""
    for a in objs:
        if a.kind in ("cloth", "arm"):
            continue  # pinned on the pole / standing on the plinth
        for ca, ra in bounds[a.inst]:
            for box in static_boxes:
                gap = np.maximum(np.abs((ca - box.c) @ box.R) - box.half, 0.0)
                if np.linalg.norm(gap) < ra + 0.03:
                    return f"{a.name} may hit the pole at frame {ti}"
    return None


def check_world(world: World, margin_px: float = 1.0) -> str | None:
    """Why the world is unusable (object out of a view, colliding, in the background), or None."""
    objs = world.objects
    static_boxes = [prim for prim in world.static if isinstance(prim, Box)]
    for ti, tau in enumerate(world.taus):
        tau = float(tau)
        ext = {o.inst: o.extent_points(tau) for o in objs}
        for o in objs:
            problem = _view_problem(world, o, ext[o.inst], ti, margin_px)
            if problem:
                return problem
        bounds = {o.inst: o.bounds(tau) for o in objs}
        problem = _collision_problem(objs, bounds, ti) or _pole_problem(objs, bounds, static_boxes, ti)
        if problem:
            return problem
    return None
