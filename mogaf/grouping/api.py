"""group_gaussians: one entry for both methods, plus flags and compaction.

Decisions (see also params.DEFAULT_PARAMS):
- Groups are dropped when they end up empty (an identity never seen, or a
  Gaga-4D group opened with Gaussians all owned elsewhere); ids are
  compacted in creation order (identity order for ours). A group of one
  Gaussian is kept.
- Identities: those listed in `instances`, plus any non-zero id found in
  the masks but not listed (unknown rigidity, name "instance<id>").
- A static scene (no foreground Gaussian moves more than static_threshold x
  scene extent over the observed steps) gives one static, rigid group with
  every Gaussian (instance id -1, name "static", source "estimated"); masks
  are not used.
- If no Gaussian is claimed by any mask, every Gaussian goes to one group
  (instance id -1, name "unlabelled") whose rigidity is estimated.
- No foreground Gaussian: zero groups.
- With split_still_members (off in the paper's setting), a group whose mask
  does not say it is rigid and that has both still and moving members gives
  its still members a static group of their own, named "<name>/still", after
  the others (a chest's body under the one foreground mask it shares with its
  lid).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..scene import Instances
from .core import Groups, InstanceTable, MaskFrames
from .gaga4d import group_gaga4d
from .ours import group_ours
from .params import load_settings, resolve_params
from .rigidity import (
    decide_rigidity,
    displacement,
    group_displacement,
    is_static_scene,
    scene_extent,
    split_still_members,
)


def instance_table(
    instances: Instances | None, masks: np.ndarray, rigid_source: list[str] | None = None
) -> InstanceTable:
    ids: list[int] = []
    names: list[str] = []
    rigid: list[int] = []
    sources: list[str] = []
    if instances is not None:
        for i, (iid, name, r) in enumerate(
            zip(np.asarray(instances.ids), instances.names, np.asarray(instances.rigid))
        ):
            if int(iid) == 0:
                continue
            ids.append(int(iid))
            names.append(str(name))
            rigid.append(int(r))
            src = rigid_source[i] if rigid_source is not None and i < len(rigid_source) else "label"
            sources.append(str(src))
    present = np.unique(np.asarray(masks)) if np.asarray(masks).size else np.zeros(0, np.int64)
    for iid in present:
        if int(iid) != 0 and int(iid) not in ids:
            ids.append(int(iid))
            names.append(f"instance{int(iid)}")
            rigid.append(-1)
            sources.append("label")
    return InstanceTable(np.asarray(ids, dtype=np.int64), names, np.asarray(rigid, dtype=np.int8), sources)


def _single_group(
    N: int, name: str, static: bool | None, rigid: int | None, p: dict, model, table, disp, extent
) -> Groups:
    """Every Gaussian in one group; static/rigid computed when None."""
    s = load_settings(p)
    group_id = np.zeros(N, dtype=np.int64)
    gi = np.array([-1], dtype=np.int64)
    if rigid is None:
        flags, sources, residual = decide_rigidity(
            gi,
            table,
            np.asarray(model.fg.means, np.float64),
            np.asarray(model.trajectory_means, np.float64),
            group_id,
            s,
        )
    else:
        flags, sources, residual = np.array([rigid], np.int8), ["estimated"], np.array([0.0])
    gdisp = group_displacement(disp, group_id, 1, float(s.static_quantile))
    if static is None:
        static = bool(gdisp[0] <= float(s.static_threshold) * extent)
    return Groups(
        group_id=group_id,
        rigid=flags,
        static=np.array([int(static)], np.int8),
        instance_id=gi,
        names=[name],
        rigid_source=sources,
        method=s.method,
        params=p,
        diagnostics={
            "group_size": np.array([N], np.int64),
            "group_displacement": gdisp,
            "group_rigid_residual": residual,
            "assignment": np.full(N, 3, np.int8),
        },
        attrs={"scene_extent": extent, "static_scene": name == "static"},
    )


def group_gaussians(
    model,
    masks: np.ndarray,
    mask_frames: MaskFrames | dict,
    instances: Instances | None,
    params: dict[str, Any] | None = None,
    *,
    rigid_source: list[str] | None = None,
    frame_order: np.ndarray | None = None,
) -> Groups:
    """Group the foreground Gaussians of `model`.

    masks (F,H,W) int instance ids (0 background) at the observed frames
    described by mask_frames (K, w2c, time_index = trajectory column);
    instances: identities with rigid flags (1/0/-1); rigid_source: where each
    known flag came from. frame_order overrides the frames visited (already
    in order; keyframes for ours, every frame for Gaga-4D).
    """
    p = resolve_params(params)
    s = load_settings(p)
    frames = mask_frames if isinstance(mask_frames, MaskFrames) else MaskFrames(**mask_frames)
    masks = np.asarray(masks)
    if masks.ndim != 3 or masks.shape[0] != len(frames):
        raise ValueError(f"masks must be (F,H,W) with F = {len(frames)} frames, got {masks.shape}")
    N = len(model.fg)
    traj = np.asarray(model.trajectory_means, dtype=np.float64)
    extent = scene_extent(traj, seed=int(s.seed))
    disp = displacement(traj)
    table = instance_table(instances, masks, rigid_source)
    if N == 0:
        e = np.zeros(0, np.int64)
        return Groups(
            group_id=e,
            rigid=np.zeros(0, np.int8),
            static=np.zeros(0, np.int8),
            instance_id=e,
            names=[],
            rigid_source=[],
            method=s.method,
            params=p,
            diagnostics={
                "group_size": e,
                "group_displacement": np.zeros(0),
                "group_rigid_residual": np.zeros(0),
                "assignment": np.zeros(0, np.int8),
            },
            attrs={"scene_extent": extent, "static_scene": True},
        )
    if is_static_scene(disp, extent, s):
        return _single_group(N, "static", True, 1, p, model, table, disp, extent)

    if s.method == "ours":
        labels, stage, diag = group_ours(model, masks, frames, table.ids, s, frame_order)
        group_inst = np.arange(len(table.ids), dtype=np.int64)
    else:
        labels, group_inst, stage, diag = group_gaga4d(model, masks, frames, table.ids, s, frame_order)
    if not np.any(labels >= 0):
        g = _single_group(N, "unlabelled", None, None, p, model, table, disp, extent)
        g.attrs["method_diagnostics"] = diag
        return g

    # Compact: drop empty groups, keep creation order.
    counts = np.bincount(labels[labels >= 0], minlength=len(group_inst))
    keep = np.flatnonzero(counts > 0)
    remap = np.full(len(group_inst), -1, dtype=np.int64)
    remap[keep] = np.arange(keep.size)
    group_id = remap[labels]
    group_inst = group_inst[keep]
    group_id, group_inst, parents = split_still_members(traj, group_id, group_inst, table.rigid, s)
    Kg = group_inst.size
    names: list[str] = []
    seen: dict[int, int] = {}
    for j in group_inst[: Kg - len(parents)]:
        n = seen.get(int(j), 0)
        seen[int(j)] = n + 1
        names.append(table.names[j] if n == 0 else f"{table.names[j]}#{n + 1}")
    names += [f"{names[k]}/still" for k in parents]
    rigid, sources, residual = decide_rigidity(
        group_inst, table, np.asarray(model.fg.means, np.float64), traj, group_id, s
    )
    gdisp = group_displacement(disp, group_id, Kg, float(s.static_quantile))
    static = (gdisp <= float(s.static_threshold) * extent).astype(np.int8)
    static[Kg - len(parents) :] = 1  # a split's still part: held still, whatever its jitter
    return Groups(
        group_id=group_id,
        rigid=rigid,
        static=static,
        instance_id=table.ids[group_inst].astype(np.int64),
        names=names,
        rigid_source=sources,
        method=s.method,
        params=p,
        diagnostics={
            "group_size": np.bincount(group_id, minlength=Kg).astype(np.int64),
            "group_displacement": gdisp,
            "group_rigid_residual": residual,
            "assignment": stage.astype(np.int8),
        },
        attrs={"scene_extent": extent, "static_scene": False, "method_diagnostics": diag},
    )
