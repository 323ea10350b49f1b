"""Parameters of the synthetic scene generator.

Every key has a default in DEFAULT_PARAMS; a params mapping may name a preset
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
from typing import Any

from ..errors import MogafError, refuse_unknown_params

DEFAULT_PARAMS: dict[str, Any] = {
    # image and sequence
    "width": 160,
    "height": 120,
    "hfov_deg": 56.0,  # horizontal field of view of all cameras
    "num_frames": 60,
    "fps": 30.0,
    "seed": 0,
    "supersample": 2,  # ss x ss rays per pixel for the RGB image
    # motion
    "speed": 1.0,  # multiplies all object motion (motion time tau = speed * t)
    "spin": 1.0,  # extra multiplier on rotation rates
    "max_travel": 0.9,  # metres: clamp on the total travel of translating objects
    "box_velocity": [0.3, -0.06, -0.05],  # m/s of motion time
    "box_spin": 1.2,  # rad/s of motion time
    "sphere_velocity": [-0.3, 0.05],  # horizontal (x, y) m/s of motion time
    "sphere_launch_vz": 1.6,  # vertical launch speed, m/s
    "gravity": 1.6,  # m/s^2 (slow-motion gravity keeps one arc in view)
    "restitution": 0.8,  # vertical speed kept at a bounce on the ground
    "sphere_spin": 3.0,  # rad/s of motion time
    "rigid_objects": True,  # the textured box and the thrown sphere (false: the non-rigid object alone)
    "nonrigid": "cloth",  # "cloth" (waving flag), "arm" (bending 2-link arm) or "articulated" (still chest, swinging lid)
    "lid_swing": 0.45,  # articulated: half the lid's swing (radians)
    "lid_rate": 1.6,  # articulated: rad/s of motion time of the swing's phase
    "cloth_amplitude": 0.09,  # metres at the free edge
    "cloth_wavelength": 0.6,  # metres
    "cloth_frequency": 0.8,  # Hz of motion time
    "num_extra_objects": 0,  # extra small rigid objects (up to 6)
    "extra_speed": 0.25,  # m/s of motion time for extra objects
    # ground truth
    "num_track_points": 256,  # GT surface points per dynamic object
    "ship_instance_masks": True,  # false: the pipeline reads the foreground mask alone (mogaf_gt keeps the ids for scoring)
    # cameras
    "camera_sweep": 0.7,  # metres the handheld train camera walks sideways
    "camera_jitter": 0.012,  # metres of handheld shake
    "test_camera_yaw_deg": [-24.0, 20.0],  # held-out cameras 1, 2 around the look-at point
}

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

MAX_EXTRA_OBJECTS = 6
NONRIGID_KINDS = ("cloth", "arm", "articulated")


def _as_float_list(key: str, value: Any, n: int) -> list[float]:
    try:
        out = [float(v) for v in value]
    except TypeError:
        raise MogafError(f"synthetic param '{key}' must be a list of {n} numbers, got {value!r}") from None
    if len(out) != n:
        raise MogafError(f"synthetic param '{key}' must have {n} numbers, got {len(out)}")
    return out


def resolve_params(params: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Defaults <- preset <- explicit params, type-checked."""
    params = dict(params or {})
    preset = params.pop("preset", "default") or "default"
    if preset not in PRESETS:
        raise MogafError(f"unknown synthetic preset '{preset}' (known: {', '.join(PRESETS)})")
    refuse_unknown_params("synthetic", params, DEFAULT_PARAMS)
    out = dict(DEFAULT_PARAMS)
    out.update(PRESETS[preset])
    out.update(params)
    for key in ("width", "height", "num_frames", "seed", "supersample", "num_extra_objects", "num_track_points"):
        value = out[key]
        if isinstance(value, bool) or int(value) != value:
            raise MogafError(f"synthetic param '{key}' must be an integer, got {value!r}")
        out[key] = int(value)
    for key, value in DEFAULT_PARAMS.items():
        if isinstance(value, float):
            try:
                out[key] = float(out[key])
            except (TypeError, ValueError):
                raise MogafError(f"synthetic param '{key}' must be a number, got {out[key]!r}") from None
        elif isinstance(value, bool):
            if not isinstance(out[key], bool):
                raise MogafError(f"synthetic param '{key}' must be true or false, got {out[key]!r}")
        elif isinstance(value, list):
            out[key] = _as_float_list(key, out[key], len(value))
    if out["width"] < 16 or out["height"] < 16:
        raise MogafError("synthetic width and height must be at least 16 pixels")
    if out["num_frames"] < 2:
        raise MogafError("synthetic num_frames must be at least 2")
    if out["fps"] <= 0 or out["speed"] <= 0 or out["spin"] < 0:
        raise MogafError("synthetic fps and speed must be positive and spin non-negative")
    if not 1 <= out["supersample"] <= 8:
        raise MogafError("synthetic supersample must be between 1 and 8")
    if not 10.0 <= out["hfov_deg"] <= 100.0:
        raise MogafError("synthetic hfov_deg must be between 10 and 100 degrees")
    if not 0 <= out["num_extra_objects"] <= MAX_EXTRA_OBJECTS:
        raise MogafError(f"synthetic num_extra_objects must be between 0 and {MAX_EXTRA_OBJECTS}")
    if out["nonrigid"] not in NONRIGID_KINDS:
        raise MogafError(f"synthetic nonrigid must be one of {', '.join(NONRIGID_KINDS)}, got {out['nonrigid']!r}")
    if out["num_track_points"] < 1:
        raise MogafError("synthetic num_track_points must be at least 1")
    if out["gravity"] <= 0 or not 0 <= out["restitution"] < 1:
        raise MogafError("synthetic gravity must be positive and restitution in [0, 1)")
    return out
