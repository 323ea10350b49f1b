"""Embedded synthetic generator: procedural dynamic scenes in the DyCheck iPhone layout.

Rendered by analytic ray casting (numpy), independent of Gaussian splatting:
a textured static ground + back wall, a textured rigid box that translates
and spins, a rigid sphere on a ballistic (optionally bouncing) arc, a
non-rigid waving cloth or bending arm, optional extra rigid objects; one
handheld-like moving train camera and two fixed held-out test cameras. Ground
truth (depth, instance ids, rigid flags, 3D trajectories of surface points and
their 2D tracks, rigid poses) is written beside the iPhone layout in
`mogaf_gt/`. See generate.py for the file layout and params.py for the knobs.
"""

from .params import DEFAULT_PARAMS, PRESETS, resolve_params

__all__ = ["DEFAULT_PARAMS", "PRESETS", "resolve_params"]
