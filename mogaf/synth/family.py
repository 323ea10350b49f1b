"""A seeded family of synthetic scenes: the benchmark forecasting changes are judged on.

`family_scenes(count, seed, contact)` draws `count` generator parameter sets,
cycling through the motion kinds of KINDS so every kind appears, each with its
own scene seed (textures, camera shake, extra objects) and draws of its
motion's strength, the sequence length and the number of held-out cameras.
The first pass over the kinds ships instance masks, the second does not, and
so on, so every kind is seen with and without masks once count >= 2 *
len(KINDS). Then come `contact` scenes of each kind of CONTACT_KINDS
(bodies that meet: they stick, or merge), kind after kind, with and without
masks in turn, numbered after the first `count`; adding them, or a kind to
them, leaves every earlier scene as it was drawn.
Each drawn scene is built (mogaf.synth.world.build_world) and redrawn while
it fails the generator's own checks (objects in view, apart), so the family
contains only scenes the pipeline can ingest.

`family_config(count, seed)` is the config layered over config/config.yaml
and config/demo.yaml that runs the family (config/family.yaml is generated
from it: `python -m mogaf.synth.family --write config/family.yaml`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..artefact import atomic_path
from ..errors import MogafError
from ..paths import read_text_file
from .params import resolve_params

# Motion kinds: (name, what it shows, drawn parameters (rng -> dict)).
KINDS: tuple[tuple[str, str, Any], ...] = (
    (
        "stop",
        "every object stops moving between the two split points (ratios 0.6 and 0.8)",
        lambda r: {"motion_stop": round(float(r.uniform(0.66, 0.78)), 3)},
    ),
    (
        "bounce",
        "the thrown sphere lands and bounces after the 0.6 split (the landing is set in seconds: in a long scene 0.8 observes it)",
        lambda r: {"sphere_launch_vz": round(float(r.uniform(1.15, 1.3)), 3)},
    ),
    (
        "spin",
        "the box spins in place, the sphere is thrown straight up",
        lambda r: {
            "box_velocity": [0.0, 0.0, 0.0],
            "box_spin": round(float(r.uniform(1.5, 2.8)), 3),
            "sphere_velocity": [0.0, 0.0],
        },
    ),
    (
        "hinge",
        "a still chest whose lid swings about a hinge, nothing else",
        lambda r: {
            "rigid_objects": False,
            "nonrigid": "articulated",
            "lid_swing": round(float(r.uniform(0.3, 0.55)), 3),
            "lid_rate": round(float(r.uniform(1.2, 2.2)), 3),
        },
    ),
    (
        "cloth",
        "a waving flag beside the rigid objects",
        lambda r: {
            "nonrigid": "cloth",
            "cloth_amplitude": round(float(r.uniform(0.07, 0.12)), 3),
            "cloth_frequency": round(float(r.uniform(0.5, 1.1)), 3),
        },
    ),
    (
        "arm",
        "a bending two-link arm beside the rigid objects",
        lambda r: {"nonrigid": "arm"},
    ),
    (
        "fast",
        "every motion 1.5-2x faster, rotations faster still",
        lambda r: {"speed": round(float(r.uniform(1.5, 2.0)), 3), "spin": round(float(r.uniform(1.2, 1.8)), 3)},
    ),
    (
        "crowd",
        "two to four extra small objects drifting through the scene",
        lambda r: {
            "num_extra_objects": int(r.integers(2, 5)),
            "extra_speed": round(float(r.uniform(0.15, 0.35)), 3),
        },
    ),
)


def _contact_time(r: np.random.Generator) -> dict[str, Any]:
    """When the bodies meet: between the two split points (0.6 and 0.8)."""
    return {"stick_time": round(float(r.uniform(0.64, 0.76)), 3)}


# Kinds where bodies meet, after the first family's: drawn after its scenes (family_scenes' `contact`).
# Each kind's scenes come after the previous kind's: appending one leaves every earlier scene as drawn.
CONTACT_KINDS: tuple[tuple[str, str, Any], ...] = (
    (
        "stick",
        "the sphere and a smaller one collide head-on between the two split points and move on as one body",
        _contact_time,
    ),
    (
        "merge",
        "two soft blobs meet between the two split points, squash into one another and move on merged",
        lambda r: {**_contact_time(r), "stick_bodies": "blobs"},
    ),
)

KIND_NAMES = tuple(k[0] for k in KINDS)
CONTACT_KIND_NAMES = tuple(k[0] for k in CONTACT_KINDS)
FRAME_COUNTS = (48, 60, 72)
# held-out camera yaws for 1, 2 and 3 cameras
CAMERA_YAWS = ((20.0,), (-24.0, 20.0), (-24.0, 20.0, -6.0))
MAX_DRAWS = 20


def _draw(draw: Any, rng: np.random.Generator, masks: bool) -> dict[str, Any]:
    params = dict(draw(rng))
    params["num_frames"] = int(rng.choice(FRAME_COUNTS))
    params["test_camera_yaw_deg"] = list(CAMERA_YAWS[int(rng.integers(0, len(CAMERA_YAWS)))])
    params["ship_instance_masks"] = masks
    return params


def _scene(i: int, seed: int, kinds: tuple[tuple[str, str, Any], ...], pass_index: int) -> tuple[str, dict[str, Any]]:
    """Scene `i` of the family: kind `pass_index % len(kinds)`, masks on even passes over `kinds`."""
    from .world import build_world

    name, _, draw = kinds[pass_index % len(kinds)]
    masks = (pass_index // len(kinds)) % 2 == 0
    rng = np.random.default_rng([int(seed), i, 4242])
    for _ in range(MAX_DRAWS):
        params = {**_draw(draw, rng, masks), "seed": int(seed) * 1000 + i}
        try:
            build_world(resolve_params(params))
        except MogafError:
            continue
        return f"f{i:02d}_{name}", params
    raise MogafError(f"scene family: no valid {name} scene in {MAX_DRAWS} draws (index {i})")


def family_scenes(count: int, seed: int = 0, contact: int = 0) -> dict[str, dict[str, Any]]:
    """{scene name: generator params} of `count` scenes of KINDS, then `contact` of
    each kind of CONTACT_KINDS; deterministic in (count, seed, contact). Names are
    `f{index:02d}_{kind}`; each scene's own `seed` is seed * 1000 + index."""
    if count < 1:
        raise MogafError(f"scene family: count must be at least 1, got {count}")
    if seed < 0:
        raise MogafError(f"scene family: seed must be >= 0, got {seed}")
    if contact < 0:
        raise MogafError(f"scene family: contact must be >= 0, got {contact}")
    drawn = [_scene(i, seed, KINDS, i) for i in range(count)]
    for k, kind in enumerate(CONTACT_KINDS):
        drawn += [_scene(count + k * contact + j, seed, (kind,), j) for j in range(contact)]
    return dict(drawn)


def family_config(
    count: int, seed: int = 0, ratios: tuple[float, ...] = (0.6, 0.8), contact: int = 0
) -> dict[str, Any]:
    """The config that runs the family through the pipeline (over config.yaml and
    demo.yaml, whose demo scene `default` stays a scene of the dataset)."""
    scenes = family_scenes(count, seed, contact)
    return {
        "datasets": {"synthetic": {"scenes": ["default", *scenes]}},
        "synthetic": scenes,
        "grid": [{"dataset": "synthetic", "scenes": list(scenes), "ratios": list(ratios)}],
        "forecast": {"methods": ["mogaf", "mogaf_paper", "constant_velocity", "frozen"]},
    }


HEADER = """\
# The scene family (mogaf.synth.family): {total} synthetic scenes drawn with seed {seed},
# {kinds} kinds of motion ({names}), each with and without instance masks,
# 48-72 frames, 1-3 held-out cameras. Generated, do not edit:
#   python -m mogaf.synth.family --count {count} --contact {contact} --seed {seed} --write config/family.yaml
# Run at ratios 0.6 and 0.8 with the demo's budgets, then the per-scene table:
#   snakemake -c2 scenes --configfile config/config.yaml config/demo.yaml config/family.yaml
# (results/tables/scenes.md; every scene and ratio is one run of the whole pipeline,
# several minutes on 2 CPU cores). Judge a forecasting change on the whole family,
# never tune a setting to one of its scenes.
"""


def family_yaml(count: int, seed: int = 0, contact: int = 0) -> str:
    """config/family.yaml's text: HEADER, then family_config as YAML (one scene a line)."""
    import yaml

    body = yaml.safe_dump(
        family_config(count, seed, contact=contact), sort_keys=False, default_flow_style=None, width=200
    )
    names = KIND_NAMES + (CONTACT_KIND_NAMES if contact else ())
    return (
        HEADER.format(
            total=count + contact * len(CONTACT_KINDS),
            count=count,
            contact=contact,
            seed=seed,
            kinds=len(names),
            names=", ".join(names),
        )
        + body
    )


def main(argv: list[str] | None = None) -> int:
    import argparse
    import sys
    from pathlib import Path

    ap = argparse.ArgumentParser(prog="python -m mogaf.synth.family", description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=24, help="scenes in the family (default 24)")
    ap.add_argument("--contact", type=int, default=4, help="scenes of each contact kind after them (default 4)")
    ap.add_argument("--seed", type=int, default=0, help="the family's seed (default 0)")
    out = ap.add_mutually_exclusive_group()
    out.add_argument("--write", metavar="FILE", help="write the config to FILE")
    out.add_argument("--check", metavar="FILE", help="exit 1 if FILE differs from the config drawn now")
    args = ap.parse_args(argv)
    try:
        text = family_yaml(args.count, args.seed, args.contact)
        if args.write:
            with atomic_path(args.write) as tmp:
                Path(tmp).write_text(text)
            print(f"wrote {args.write}")
        elif args.check:
            if read_text_file(args.check) != text:
                raise MogafError(f"{args.check}: differs from the family drawn now; rewrite it with --write")
        else:
            print(text, end="")
    except MogafError as exc:
        print(f"mogaf.synth.family: error: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
