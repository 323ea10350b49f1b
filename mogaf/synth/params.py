"""Parameters of the synthetic scene generator.

Every key is a field of SyntheticSettings (DEFAULT_PARAMS as a dict); a params mapping may name a preset
("preset": "hard") whose values override the defaults, and explicit keys
override the preset. Unknown keys are refused so a typo in a config is an
error, not a silent default.

Time: frame i is at t_i = i / fps seconds. Object motion is evaluated at
"motion time" tau = speed * t, so `speed` makes every object (translation,
spin, fall, waving) proportionally faster; `spin` scales rotation rates on top
of that. Translations are centred on the sequence (the middle frame sits at
the nominal position) and their total travel is clamped (`max_travel`) so
objects stay in every camera's view for any sequence length.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

from ..errors import MogafError
from ..settings import check, defaults, setting


@dataclass(frozen=True)
class SyntheticSettings:
    """Settings of the synthetic scene generator (one entry of the config section `synthetic`, over its preset)."""

    # image and sequence
    width: int = setting(160, "image width (px)", minimum=16)
    height: int = setting(120, "image height (px)", minimum=16)
    hfov_deg: float = setting(56.0, "horizontal field of view of all cameras", minimum=10.0, maximum=100.0)
    num_frames: int = setting(60, "frames in the sequence", minimum=2)
    fps: float = setting(30.0, "frame i is at t_i = i / fps seconds", exclusive_minimum=0)
    seed: int = setting(0, "seed of the scene's randomness (textures, extra objects, camera shake)", minimum=0)
    supersample: int = setting(2, "ss x ss rays per pixel for the RGB image", minimum=1, maximum=8)
    # motion
    speed: float = setting(1.0, "multiplies all object motion (motion time tau = speed * t)", exclusive_minimum=0)
    motion_stop: float = setting(
        1.0,
        "share of the sequence after which every object holds its pose (1 = moves to the end)",
        exclusive_minimum=0,
        maximum=1,
    )
    spin: float = setting(1.0, "extra multiplier on rotation rates", minimum=0)
    max_travel: float = setting(0.9, "metres: clamp on the total travel of translating objects")
    box_velocity: list = setting([0.3, -0.06, -0.05], "m/s of motion time")
    box_spin: float = setting(1.2, "rad/s of motion time")
    sphere_velocity: list = setting([-0.3, 0.05], "horizontal (x, y) m/s of motion time")
    sphere_launch_vz: float = setting(1.6, "vertical launch speed, m/s")
    gravity: float = setting(1.6, "m/s^2 (slow-motion gravity keeps one arc in view)", exclusive_minimum=0)
    restitution: float = setting(0.8, "vertical speed kept at a bounce on the ground", minimum=0, exclusive_maximum=1)
    sphere_spin: float = setting(3.0, "rad/s of motion time")
    rigid_objects: bool = setting(True, "the textured box and the thrown sphere (false: the non-rigid object alone)")
    nonrigid: Literal["cloth", "arm", "articulated"] = setting(
        "cloth", '"cloth" (waving flag), "arm" (bending 2-link arm) or "articulated" (still chest, swinging lid)'
    )
    lid_swing: float = setting(0.45, "articulated: half the lid's swing (radians)")
    lid_rate: float = setting(1.6, "articulated: rad/s of motion time of the swing's phase")
    cloth_amplitude: float = setting(0.09, "metres at the free edge")
    cloth_wavelength: float = setting(0.6, "metres")
    cloth_frequency: float = setting(0.8, "Hz of motion time")
    stick_time: float = setting(
        0.0,
        "share of the sequence at which the sphere meets a second, smaller sphere head-on and the two move on as one "
        "body, with their momentum, spinning no more (0 = no second sphere; the sphere is thrown as usual)",
        minimum=0,
        exclusive_maximum=1,
    )
    stick_bodies: Literal["spheres", "blobs"] = setting(
        "spheres",
        'what meets at stick_time: "spheres" (rigid, they stick) or "blobs" (two soft balls in their place that '
        "squash into one another at the contact and move on merged)",
    )
    num_extra_objects: int = setting(0, "extra small rigid objects (up to 6)", minimum=0, maximum=6)
    extra_speed: float = setting(0.25, "m/s of motion time for extra objects")
    # ground truth
    num_track_points: int = setting(256, "GT surface points per dynamic object", minimum=1)
    ship_instance_masks: bool = setting(
        True, "false: the pipeline reads the foreground mask alone (mogaf_gt keeps the ids for scoring)"
    )
    # cameras
    camera_sweep: float = setting(0.7, "metres the handheld train camera walks sideways")
    camera_jitter: float = setting(0.012, "metres of handheld shake")
    test_camera_yaw_deg: list = setting(
        [-24.0, 20.0], "yaw of each held-out camera (1 to 3 of them) around the look-at point"
    )


DEFAULT_PARAMS: dict[str, Any] = defaults(SyntheticSettings)

PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    # Faster translation and spin, more objects, longer sequence, and the
    # sphere bounces (twice) within the sequence, once in the forecast part.
    "hard": {
        "num_frames": 90,
        "speed": 1.8,
        "spin": 1.5,
        "max_travel": 0.9,
        "num_extra_objects": 3,
        "cloth_amplitude": 0.11,
    },
    # A still body with one moving part and nothing else (the D-NeRF-style case
    # where most of an object stays put); it ships no instance masks, so the
    # pipeline sees the foreground mask alone, like a real capture.
    "articulated": {
        "rigid_objects": False,
        "nonrigid": "articulated",
        "ship_instance_masks": False,
    },
    # The sphere is thrown lower, so it lands after the split (frame 52 of 60;
    # ratios 0.6 and 0.8 observe 36 and 48): the bounce is in the future.
    "bounce": {
        "sphere_launch_vz": 1.25,
    },
}


# (distance factor, height offset, roll) of held-out cameras 1, 2, 3: a yaw list
# of test_camera_yaw_deg places that many (mogaf.synth.world.build_world)
TEST_CAMERA_PLACES = ((1.0, -0.12, 0.015), (1.05, 0.2, -0.02), (0.95, 0.04, 0.0))


def _as_float_list(key: str, value: Any, n: int) -> list[float]:
    try:
        out = [float(v) for v in value]
    except TypeError:
        raise MogafError(f"synthetic param '{key}' must be a list of {n} numbers, got {value!r}") from None
    if len(out) != n:
        raise MogafError(f"synthetic param '{key}' must have {n} numbers, got {len(out)}")
    return out


def load_settings(params: Mapping[str, Any] | SyntheticSettings | None) -> SyntheticSettings:
    """resolve_params as a frozen SyntheticSettings (what the generator reads)."""
    if isinstance(params, SyntheticSettings):
        return params
    return SyntheticSettings(**resolve_params(params))


def resolve_params(params: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Defaults <- preset <- explicit params, checked (SyntheticSettings)."""
    params = dict(params or {})
    preset = params.pop("preset", "default") or "default"
    if preset not in PRESETS:
        raise MogafError(f"unknown synthetic preset '{preset}' (known: {', '.join(PRESETS)})")
    # the preset's values are checked (and converted) like explicit ones
    out = check(SyntheticSettings, "synthetic", {**PRESETS[preset], **params})
    for key, value in DEFAULT_PARAMS.items():
        if isinstance(value, list) and key != "test_camera_yaw_deg":
            out[key] = _as_float_list(key, out[key], len(value))
    yaws = out["test_camera_yaw_deg"]
    if not isinstance(yaws, (list, tuple)) or not 1 <= len(yaws) <= len(TEST_CAMERA_PLACES):
        raise MogafError(
            f"synthetic param 'test_camera_yaw_deg' must be a list of 1 to {len(TEST_CAMERA_PLACES)} numbers"
        )
    out["test_camera_yaw_deg"] = _as_float_list("test_camera_yaw_deg", yaws, len(yaws))
    return out
