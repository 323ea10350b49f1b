"""Stage entries: group (-> groups.h5) and rigid_init (-> rigid.h5).

groups.h5 (stage "group"):
  group_id (N_fg,) int64 in [0, K)
  group_rigid (K,) int8             tau_k: 1 rigid, 0 non-rigid
  group_static (K,) int8            1: the group barely moves (forecasting skips it)
  group_instance_id (K,) int64      mask identity the group came from (-1: none)
  group_names [K str]               instance names ("name#2" for a second Gaga-4D fragment)
  group_rigid_source [K str]        "label" | "config" | "estimated"
  diagnostics/group_size (K,), diagnostics/group_displacement (K,) (static_quantile
    of member displacement, scene units), diagnostics/group_rigid_residual (K,)
    (relative residual of the rigidity estimate, -1 where a label decided),
    diagnostics/assignment (N,) int8 (0 seeded by a mask, 1 region growing,
    2 KNN voting, 3 single-group fallback)
  attrs: method, params (JSON), num_groups, scene_extent, static_scene,
    method_diagnostics (JSON)
The grouping's quality against GT instance masks at held-out views is
measured by its own stage (mogaf.grouping.quality), not here: the group
stage reads only the observed frames' masks and cameras.

rigid.h5 (stage "rigid_init"), supplementary "Rigid Motion Initialization":
  group_ids (K_r,) int64            the rigid groups
  rotations (K_r,T,3,3), translations (K_r,T,3)
                                    mu_t ~= R mu_canonical + t at every observed step
  residual_rms (K_r,T)              RMS distance of the members to the fit (scene units)
  timesteps (T,) int64              the model's observed steps
  attrs: params (JSON), weights
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..artefact import config_digest, open_artefact, read_artefact, read_rows, write_artefact
from ..errors import MogafError, input_error
from ..representation import load_model
from ..rigid_fit import fit_residual, procrustes
from ..scene import SCENE_STAGE, Instances
from ..settings import as_dict, load
from .core import GROUP_STAGE, Groups, MaskFrames, frames_in_time_order
from .params import RigidInitSettings, _typed_params, load_settings, resolve_params

log = logging.getLogger("mogaf.grouping")

RIGID_STAGE = "rigid_init"
PRIORS_STAGE = "priors"


# ---------------------------------------------------------------- groups.h5
def _strings(values: list[str]) -> Any:
    return list(values) if values else np.zeros(0, "U1")


def write_groups(path: str | os.PathLike, groups: Groups, *, digest: str | None = None) -> Path:
    diag = {k: np.asarray(v) for k, v in groups.diagnostics.items()}
    data: dict[str, Any] = {
        "group_id": np.asarray(groups.group_id, dtype=np.int64),
        "group_rigid": np.asarray(groups.rigid, dtype=np.int8),
        "group_static": np.asarray(groups.static, dtype=np.int8),
        "group_instance_id": np.asarray(groups.instance_id, dtype=np.int64),
        "group_names": _strings(groups.names),
        "group_rigid_source": _strings(groups.rigid_source),
        "diagnostics": diag,
    }
    attrs = {
        "method": groups.method,
        "params": groups.params,
        "num_groups": groups.num_groups,
        **dict(groups.attrs),
    }
    digest = digest or config_digest(groups.params)
    return write_artefact(path, GROUP_STAGE, data, config_digest=digest, attrs=attrs)


def _str_list(x: Any) -> list[str]:
    if isinstance(x, np.ndarray):
        return [str(v) for v in x.tolist()] if x.dtype.kind in "USO" else []
    if isinstance(x, (list, tuple)):
        return [str(v) for v in x]
    return [str(x)]


def load_groups(path: str | os.PathLike) -> Groups:
    art = read_artefact(path, GROUP_STAGE, required=["group_id", "group_rigid", "group_static", "group_instance_id"])
    g = Groups(
        group_id=np.asarray(art["group_id"], dtype=np.int64),
        rigid=np.asarray(art["group_rigid"], dtype=np.int8),
        static=np.asarray(art["group_static"], dtype=np.int8),
        instance_id=np.asarray(art["group_instance_id"], dtype=np.int64),
        names=_str_list(art.get("group_names", [])),
        rigid_source=_str_list(art.get("group_rigid_source", [])),
        method=str(art.attrs.get("method", "")),
        params=_typed_params(dict(art.attrs.get("params") or {})),
        diagnostics=dict(art.get("diagnostics", {}) or {}),
        attrs={k: v for k, v in art.attrs.items() if k not in ("method", "params")},
    )
    K = g.num_groups
    if g.static.size != K or g.instance_id.size != K:
        raise input_error(path, "group arrays disagree in length")
    if g.group_id.size and (g.group_id.min() < 0 or g.group_id.max() >= K):
        raise input_error(path, f"group_id outside [0, {K})")
    return g


# ---------------------------------------------------------------- group stage
def _decode(values) -> list[str]:
    return [v.decode() if isinstance(v, bytes) else str(v) for v in np.asarray(values).tolist()]


def read_priors_for_grouping(priors_h5: str | os.PathLike) -> dict[str, Any]:
    """frame_ids, timesteps, instance table and an accessor of mask rows."""
    with open_artefact(priors_h5, PRIORS_STAGE) as fh:
        out: dict[str, Any] = {
            "frame_ids": np.asarray(fh["frame_ids"][()], dtype=np.int64),
            "timesteps": np.asarray(fh["timesteps"][()], dtype=np.int64),
            "has_instance_masks": "masks/instance" in fh,
            "has_foreground": "masks/foreground" in fh,
        }
        if "instances/ids" in fh:
            out["instances"] = Instances(
                ids=np.asarray(fh["instances/ids"][()]),
                names=_decode(fh["instances/names"][()])
                if "instances/names" in fh
                else [f"instance{int(i)}" for i in fh["instances/ids"][()]],
                rigid=np.asarray(fh["instances/rigid"][()])
                if "instances/rigid" in fh
                else np.full(fh["instances/ids"].shape[0], -1),
            )
            src = _decode(fh["instances/rigid_source"][()]) if "instances/rigid_source" in fh else []
            out["rigid_source"] = ["config" if s == "config" else "label" for s in src]
    return out


def read_mask_rows(priors_h5: str | os.PathLike, rows: np.ndarray) -> tuple[np.ndarray, bool]:
    """Instance masks of the given priors rows, or the foreground mask as identity 1."""
    with open_artefact(priors_h5, PRIORS_STAGE) as fh:
        if "masks/instance" in fh:
            return read_rows(fh, "masks/instance", rows).astype(np.int32), True
        if "masks/foreground" in fh:
            return (read_rows(fh, "masks/foreground", rows) > 0).astype(np.int32), False
    raise input_error(priors_h5, "has neither masks/instance nor masks/foreground")


def run_group_stage(recon_h5, priors_h5, scene_h5, out_h5, params: dict[str, Any] | None = None) -> Path:
    """Group the reconstruction's Gaussians by the observed frames' masks; write groups.h5."""
    # local: the grouping methods load scipy.spatial, which rigid_init, refine's
    # readers and grouping_quality (importers of this module) do not need
    from .api import group_gaussians
    from .ours import keyframe_order

    p = resolve_params(params)
    s = load_settings(p)
    model = load_model(recon_h5)
    pri = read_priors_for_grouping(priors_h5)
    steps = np.asarray(model.timesteps, dtype=np.int64)
    col_of = {int(s): i for i, s in enumerate(steps)}
    missing = sorted({int(t) for t in pri["timesteps"]} - set(col_of))
    if missing:
        raise input_error(priors_h5, f"mask frames at time steps {missing[:5]} are not observed steps of {recon_h5}")
    if s.method == "ours":
        order = keyframe_order(pri["timesteps"], s.keyframe_stride)
    else:
        order = frames_in_time_order(pri["timesteps"])[:: int(s.gaga_frame_stride)]
    rows, inverse = np.unique(order, return_inverse=True)
    masks, from_instances = read_mask_rows(priors_h5, rows)
    instances = pri.get("instances") if from_instances else Instances(ids=[1], names=["foreground"], rigid=[-1])
    rigid_source = pri.get("rigid_source") if from_instances else None
    with open_artefact(scene_h5, SCENE_STAGE) as fh:
        K = read_rows(fh, "frames/K", pri["frame_ids"][rows])
        w2c = read_rows(fh, "frames/w2c", pri["frame_ids"][rows])
    frames = MaskFrames(K=K, w2c=w2c, time_index=np.array([col_of[int(t)] for t in pri["timesteps"][rows]]))
    groups = group_gaussians(
        model, masks, frames, instances, p, rigid_source=rigid_source, frame_order=np.asarray(inverse).reshape(-1)
    )
    del masks
    log.info(
        "grouping (%s): %d groups, sizes %s, rigid %s, static %s",
        s.method,
        groups.num_groups,
        groups.sizes().tolist(),
        groups.rigid.tolist(),
        groups.static.tolist(),
    )
    return write_groups(out_h5, groups, digest=config_digest(p))


# ---------------------------------------------------------------- rigid_init stage
def rigid_init(model, groups: Groups, params: dict[str, Any] | None = None) -> dict[str, np.ndarray]:
    """Per rigid group and observed step: (R, t) canonical -> deformed means."""
    p = load(RigidInitSettings, "rigid_init", params)
    N, T = model.trajectory_means.shape[:2]
    if groups.group_id.size != N:
        raise MogafError(f"rigid_init: groups cover {groups.group_id.size} Gaussians, the model has {N}")
    rigid_ids = np.flatnonzero(np.asarray(groups.rigid) == 1).astype(np.int64)
    Kr = rigid_ids.size
    rot = np.tile(np.eye(3), (Kr, T, 1, 1))
    trans = np.zeros((Kr, T, 3))
    res = np.zeros((Kr, T))
    chunk = max(int(p.time_chunk), 1)
    canonical = np.asarray(model.fg.means, dtype=np.float64)
    for i, k in enumerate(rigid_ids):
        members = groups.members(int(k))
        if members.size == 0:
            continue
        src = canonical[members]
        w = None
        if p.weights == "opacity":
            w = 1.0 / (1.0 + np.exp(-np.asarray(model.fg.opacity_logits, np.float64)[members]))
        for t0 in range(0, T, chunk):
            dst = np.transpose(
                np.asarray(model.trajectory_means[members, t0 : t0 + chunk], dtype=np.float64), (1, 0, 2)
            )
            R, t = procrustes(src, dst, w)
            rot[i, t0 : t0 + chunk] = R
            trans[i, t0 : t0 + chunk] = t
            res[i, t0 : t0 + chunk] = fit_residual(src, dst, w, R, t)
    return {
        "group_ids": rigid_ids,
        "rotations": rot,
        "translations": trans,
        "residual_rms": res,
        "timesteps": np.asarray(model.timesteps, dtype=np.int64),
    }


def run_rigid_init_stage(model_h5, groups_h5, out_h5, params: dict[str, Any] | None = None) -> Path:
    p = load(RigidInitSettings, "rigid_init", params)
    model = load_model(model_h5)
    groups = load_groups(groups_h5)
    data = rigid_init(model, groups, p)
    if data["group_ids"].size == 0:
        log.warning("rigid_init: %s has no rigid group; writing an empty rigid.h5", groups_h5)
    else:
        log.info(
            "rigid_init: %d rigid groups, mean residual %.4g",
            data["group_ids"].size,
            float(data["residual_rms"].mean()),
        )
    return write_artefact(
        out_h5,
        RIGID_STAGE,
        data,
        config_digest=config_digest(as_dict(p)),
        attrs={"params": as_dict(p), "weights": p.weights},
    )


def read_rigid_init(path: str | os.PathLike) -> dict[str, np.ndarray]:
    art = read_artefact(path, RIGID_STAGE, required=["group_ids", "rotations", "translations", "residual_rms"])
    return {
        k: np.asarray(art[k])
        for k in ("group_ids", "rotations", "translations", "residual_rms", "timesteps")
        if k in art
    }
