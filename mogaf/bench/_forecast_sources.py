"""Ground-truth trajectory sources of `python -m mogaf.bench forecast`.

The embedded synthetic scenes, one set per object (synthetic_default,
synthetic_hard, synthetic_articulated, synthetic_bounce: use them as
`--source mogaf.bench.forecast:synthetic_default`), and the loader of a
--source MODULE:FUNCTION.
"""

from __future__ import annotations

import hashlib
import importlib
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from mogaf.errors import MogafError
from mogaf.forecast import quat
from mogaf.paths import cache_dir


def _local_rotations(points: np.ndarray, k: int = 8) -> np.ndarray:
    """(P, T, 4) wxyz rotation of each point's k-neighbourhood (nearest at
    frame 0) from frame 0 to every frame: the best rigid fit, det = +1."""
    from scipy.spatial import cKDTree

    from mogaf.representation import matrix_to_quat_numpy  # local, as procrustes_numpy
    from mogaf.rigid import procrustes_numpy  # local: mogaf.rigid imports torch, which only this path needs

    k = min(k + 1, points.shape[0])
    _, nn = cKDTree(points[:, 0]).query(points[:, 0], k=k)
    src = points[nn, 0][:, None]  # (P, 1, k, 3)
    dst = points[nn].transpose(0, 2, 1, 3)  # (P, T, k, 3)
    R, _ = procrustes_numpy(src, dst)
    return quat.make_continuous(matrix_to_quat_numpy(R), axis=1)


def code_digest(root: str | os.PathLike | None = None) -> str:
    """A digest (16 hex digits of sha256) of the Python sources under `root`
    (default: the mogaf package): the code a --json file's rows were computed
    by, or the generator code a cached scene was made by."""
    root = Path(__file__).resolve().parents[1] if root is None else Path(root)
    h = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*.py") if p.is_file()):  # not an editor's dangling link
        h.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def synthetic_scene_sets(preset: str = "default") -> dict[str, np.ndarray]:
    """Ground-truth trajectories of the embedded synthetic scene, one set per
    object (the group-wise setting): (P_obj, T, 7) [surface point, rotation].
    Rotations: the object pose for rigid objects, the local best rigid fit of
    the point's neighbourhood for non-rigid ones. The scene is generated into
    the cache once per version of the generator's code (mogaf/synth)."""
    import json as _json

    import mogaf.synth
    from mogaf.representation import matrix_to_quat_numpy  # local: it imports h5py (artefacts)
    from mogaf.synth.generate import generate_scene  # local: mogaf.synth imports cv2, which only this path needs

    code = code_digest(Path(mogaf.synth.__file__).parent)  # other generator code: the scene made again
    root = cache_dir("bench_forecast", f"synthetic_{preset}_{code}")
    if not (root / "mogaf_gt" / "points3d.npy").exists():
        generate_scene(root, {"preset": preset})
    gt = root / "mogaf_gt"
    points = np.load(gt / "points3d.npy").astype(np.float64)
    inst = np.load(gt / "points_instance.npy")
    poses = np.load(gt / "object_poses.npy")
    objects = _json.loads((gt / "instances.json").read_text())["instances"]
    out = {}
    for obj in objects:
        oid = int(obj["id"])
        if oid == 0:
            continue
        sel = np.flatnonzero(inst == oid)
        if sel.size < 2:
            continue
        if int(obj.get("pose_index", -1)) >= 0:
            R = poses[int(obj["pose_index"])][:, :3, :3]  # (T, 3, 3)
            q = quat.make_continuous(np.repeat(matrix_to_quat_numpy(R)[None], sel.size, axis=0), axis=1)
        else:
            q = _local_rotations(points[sel])
        out[f"{preset}/{obj['name']}"] = np.concatenate([points[sel], q], axis=-1)
    return out


def synthetic_default() -> dict[str, np.ndarray]:
    return synthetic_scene_sets("default")


def synthetic_hard() -> dict[str, np.ndarray]:
    return synthetic_scene_sets("hard")


def synthetic_articulated() -> dict[str, np.ndarray]:
    return synthetic_scene_sets("articulated")


def synthetic_bounce() -> dict[str, np.ndarray]:
    return synthetic_scene_sets("bounce")


def _load_source(spec: str) -> dict[str, Any]:
    mod_name, _, func_name = spec.partition(":")
    if not func_name:
        raise MogafError(f"bench forecast: --source must be MODULE:FUNCTION, got '{spec}'")
    try:
        obj = getattr(importlib.import_module(mod_name), func_name)()
    except (ImportError, AttributeError) as exc:
        raise MogafError(f"bench forecast: cannot load --source {spec} ({exc})") from None
    if isinstance(obj, Mapping):
        return dict(obj)
    return {func_name: obj}
