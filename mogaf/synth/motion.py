"""Motions of the synthetic objects, as functions of motion time tau.

Rotation about an axis (Rodrigues; also used to aim the cameras), a uniform
drift centred on the sequence (_linear, its speed clamped by
_clamped_velocity) and the ballistic arc of a thrown sphere bouncing on the
ground (Ballistic), the path of one of two bodies that collide and stick
(StuckPath) and of two soft bodies that merge (MergePath).
"""

from __future__ import annotations

import numpy as np

from ..errors import MogafError


def rotation(axis, angle) -> np.ndarray:
    """Rodrigues rotation matrix about `axis` by `angle` (radians)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * (K @ K)


def _clamped_velocity(v: np.ndarray, tau_max: float, max_travel: float) -> np.ndarray:
    travel = float(np.linalg.norm(v)) * tau_max
    return v * min(1.0, max_travel / travel) if travel > 0 else v


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


class StuckPath:
    """Centre of a body that moves uniformly until it sticks to another at
    motion time tau_contact, then moves on with the pair's common velocity:
    c(tau) = contact + v (tau - tau_contact), v = v_before before the contact
    and v_after from it on (continuous at the contact)."""

    def __init__(self, contact, v_before, v_after, tau_contact: float):
        self.contact = np.asarray(contact, float)
        self.v_before, self.v_after = np.asarray(v_before, float), np.asarray(v_after, float)
        self.tau_contact = float(tau_contact)

    def __call__(self, tau: float) -> np.ndarray:
        v = self.v_before if tau < self.tau_contact else self.v_after
        return self.contact + v * (tau - self.tau_contact)


class MergePath:
    """Centres and squash of two soft bodies that meet at motion time
    tau_contact and merge: before it each moves uniformly (v_a, v_b, head-on
    along the unit vector n from a to b); from it on their common centre of
    mass moves with the momentum-weighted velocity while they keep closing in,
    at a speed falling linearly to zero, until their centres are `overlap`
    of the contact distance nearer; they move on as one after that. Every
    centre's velocity is continuous at the contact.

    merged(tau) is how far the merge has got, 0 before the contact to 1 from
    its end: 1 - (1 - s)^2 of the elapsed share s."""

    def __init__(self, contact_a, contact_b, v_a, v_b, masses, tau_contact: float, overlap: float):
        self.contact_a, self.contact_b = np.asarray(contact_a, float), np.asarray(contact_b, float)
        self.v_a, self.v_b = np.asarray(v_a, float), np.asarray(v_b, float)
        self.tau_contact = float(tau_contact)
        gap = self.contact_b - self.contact_a
        self.contact_distance = float(np.linalg.norm(gap))
        self.n = gap / self.contact_distance
        m = np.asarray(masses, float)
        self.share = m / m.sum()  # each body's share of the mass
        self.v_after = self.share[0] * self.v_a + self.share[1] * self.v_b
        closing = float((self.v_a - self.v_b) @ self.n)
        # head-on (both velocities along n), so each centre's velocity is continuous at the contact
        sideways = (self.v_a - self.v_b) - closing * self.n
        if closing <= 0 or np.linalg.norm(sideways) > 1e-9 * abs(closing):
            raise MogafError("MergePath: the two bodies must close in head-on")
        self.depth = overlap * self.contact_distance
        # constant deceleration: closing speed at the contact -> 0 over the merge
        self.duration = 2.0 * self.depth / closing

    def merged(self, tau: float) -> float:
        s = min(max((tau - self.tau_contact) / self.duration, 0.0), 1.0)
        return 1.0 - (1.0 - s) ** 2

    def centre(self, body: int, tau: float) -> np.ndarray:
        dt = tau - self.tau_contact
        if dt < 0:
            return (self.contact_a, self.contact_b)[body] + (self.v_a, self.v_b)[body] * dt
        mass_centre = self.share[0] * self.contact_a + self.share[1] * self.contact_b + self.v_after * dt
        gap = self.contact_distance - self.depth * self.merged(tau)
        # body a sits the other body's share of the gap behind the centre of mass, b ahead by a's share
        return mass_centre + (-self.share[1] if body == 0 else self.share[0]) * gap * self.n
