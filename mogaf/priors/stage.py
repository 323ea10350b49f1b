"""The priors stage: build_priors (pure) and writing priors.h5.

See the mogaf.priors package docstring for the sources and the artefact
layout; the parameters are in mogaf.priors.params.
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..artefact import config_digest as _config_digest
from ..artefact import write_artefact
from ..errors import MogafError
from ..scene import Scene
from ..split import Split, load_frames, read_split
from .depth import select_depth
from .file_tracks import _composite_tracks, _ground_truth_tracks, _shipped_tracks
from .flow import consecutive_flows
from .instances import cluster_tracks, label_pixels
from .masks import background_colour_mask, motion_segmentation, static_tracks
from .params import PriorsSettings, load_settings, resolve_params
from .shipped import load_observed_ground_truth_tracks, load_observed_shipped
from .tracks import Tracks, compute_flow_tracks, track_statistics

STAGE = "priors"

NO_TRACKS_DNERF = "none (layout dnerf: the camera teleports between views, consecutive-frame flow is meaningless)"


@dataclass
class PriorsResult:
    dataset: str
    scene: str
    layout: str
    ratio: float
    frame_ids: np.ndarray  # (F_o,) int64
    timesteps: np.ndarray  # (F_o,) int64
    foreground: np.ndarray  # (F_o, H, W) uint8
    instance_mask: np.ndarray | None = None  # (F_o, H, W) int32
    instance_ids: np.ndarray | None = None
    instance_names: list[str] | None = None
    instance_rigid: np.ndarray | None = None
    instance_rigid_source: list[str] | None = None
    depth: np.ndarray | None = None  # (F_o, H, W) float32
    depth_valid: np.ndarray | None = None  # (F_o, H, W) uint8
    depth_kind: str = "none"
    tracks: Tracks | None = None
    track_instance: np.ndarray | None = None  # (P,) int64
    sources: dict[str, str] = field(default_factory=dict)
    track_stats: dict[str, Any] = field(default_factory=dict)
    shipped_ignored: list[str] = field(default_factory=list)
    seconds: float = 0.0

    def to_data(self) -> dict[str, Any]:
        data: dict[str, Any] = {
            "frame_ids": np.asarray(self.frame_ids, np.int64),
            "timesteps": np.asarray(self.timesteps, np.int64),
            "masks": {"foreground": np.asarray(self.foreground, np.uint8)},
        }
        if self.instance_mask is not None and self.instance_ids is not None:
            data["masks"]["instance"] = np.asarray(self.instance_mask, np.int32)
            counts = [int((self.instance_mask == i).sum()) for i in self.instance_ids]
            data["instances"] = {
                "ids": np.asarray(self.instance_ids, np.int64),
                "names": list(self.instance_names or []) or np.zeros(0, "U1"),
                "rigid": np.asarray(self.instance_rigid, np.int8),
                "rigid_source": list(self.instance_rigid_source or []) or np.zeros(0, "U1"),
                "num_pixels": np.asarray(counts, np.int64),
            }
        if self.depth is not None:
            data["depth"] = {
                "values": np.asarray(self.depth, np.float32),
                "valid": np.asarray(self.depth_valid, np.uint8),
            }
        if self.tracks is not None:
            tr = self.tracks
            data["tracks"] = {
                "query_index": np.asarray(tr.query_index, np.int64),
                "xy": np.asarray(tr.xy, np.float32),
                "visible": np.asarray(tr.visible, np.uint8),
                "confidence": np.asarray(tr.confidence, np.float32),
            }
            if tr.fb_error is not None:
                data["tracks"]["fb_error"] = np.asarray(tr.fb_error, np.float32)
            if self.track_instance is not None:
                data["tracks"]["instance"] = np.asarray(self.track_instance, np.int64)
        return data

    def attrs(self) -> dict[str, Any]:
        st = self.track_stats
        out = {
            "dataset": self.dataset,
            "scene": self.scene,
            "layout": self.layout,
            "ratio": float(self.ratio),
            "num_observed_frames": int(len(self.frame_ids)),
            "sources": dict(self.sources),
            "depth_kind": self.depth_kind,
            "seconds": round(float(self.seconds), 3),
            "shipped_ignored": list(self.shipped_ignored),
        }
        # Track statistics as numeric scalar attrs track_<name>.
        for key, value in st.items():
            if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
                out[f"track_{key}"] = value
        out["track_count"] = int(st.get("count", 0))
        out["track_mean_length"] = float(st.get("mean_length", 0.0))
        out["track_fb_error_median_px"] = float(st.get("fb_error_median_px", -1.0))
        out["track_fb_error_p95_px"] = float(st.get("fb_error_p95_px", -1.0))
        return out


def _shipped_foreground(shipped: Mapping[str, Any]) -> np.ndarray | None:
    entry = shipped.get("foreground")
    if isinstance(entry, Mapping) and "values" in entry:
        arr = np.asarray(entry["values"])
        if arr.ndim == 4:
            arr = arr[..., 0]
        return arr > 0
    return None


def _file_tracks(
    scene_h5: str | os.PathLike, split: Split, shipped: Mapping[str, Any], timesteps: np.ndarray, p: PriorsSettings
) -> tuple[Tracks | None, str | None]:
    """Tracks from files (shipped, else ground truth) and their source; (None, None) where there are none."""
    tracks = _shipped_tracks(shipped, p)
    if tracks is not None:
        return tracks, "shipped"
    gt = load_observed_ground_truth_tracks(scene_h5, split)
    tracks = _ground_truth_tracks(gt, split, timesteps, p)
    if tracks is not None:
        return tracks, "ground_truth"
    return None, None


def _single_foreground(scene: Scene, p: PriorsSettings) -> bool:
    """A dataset "instance" mask with the single instance "foreground" (the
    iPhone reader's Shape-of-Motion track_anything mask) is a foreground
    mask: instances then come from clustering the tracks inside it."""
    return bool(
        p.cluster_single_foreground
        and scene.layout == "iphone"
        and scene.instance_mask is not None
        and scene.instances is not None
        and len(scene.instances.ids) == 1
        and scene.instances.names[0].lower() == "foreground"
    )


def _given_foreground(
    scene_h5: str | os.PathLike, scene: Scene, shipped: Mapping[str, Any], single_fg: bool
) -> tuple[np.ndarray | None, str | None]:
    """(F, H, W) foreground the inputs give (dataset masks, shipped masks, alpha) and its source; (None, None) if none."""
    if scene.instance_mask is not None:
        return scene.instance_mask > 0, "dataset_foreground_mask" if single_fg else "dataset_instance_masks"
    fg = _shipped_foreground(shipped)
    if fg is not None:
        want = (scene.num_frames, scene.height, scene.width)
        if fg.shape != want:
            raise MogafError(f"{scene_h5}: shipped masks have shape {fg.shape}, expected {want}")
        return fg, "shipped_masks"
    if scene.alpha is not None and np.any(scene.alpha < 255):
        return scene.alpha >= 128, "alpha"
    return None, None


def _derived_foreground(
    scene: Scene, order: np.ndarray, flows: tuple, p: PriorsSettings
) -> tuple[np.ndarray, np.ndarray | None, str]:
    """(foreground, camera motion per step or None, source) where the inputs give none: motion
    segmentation of a monocular video, else the background colour, else the whole frame."""
    if scene.layout == "iphone":
        fg_sorted, cams = motion_segmentation(*flows, p)
        fg = np.empty_like(fg_sorted)
        fg[order] = fg_sorted
        return fg, cams, f"motion_segmentation ({p.flow_method} flow, {p.motion_camera_model} camera)"
    if scene.meta.get("background") is not None:
        return background_colour_mask(scene.images, scene.meta["background"]), None, "background_colour"
    return np.ones((scene.num_frames, scene.height, scene.width), bool), None, "none (whole frame)"


def _flow_tracks(
    frames_sorted: np.ndarray,
    fg: np.ndarray,
    order: np.ndarray,
    flows: tuple,
    flow_seconds: float,
    cams: np.ndarray | None,
    p: PriorsSettings,
) -> tuple[Tracks, dict[str, Any], np.ndarray | None]:
    """(tracks, their statistics, which are static or None) computed from the optical flow; static
    tracks are found where the foreground came from motion segmentation (camera motion `cams`)."""
    tr_sorted = compute_flow_tracks(frames_sorted, fg[order], p, flows=flows)
    static = None  # computed tracks that do not move beyond the camera (motion-segmented scenes)
    if cams is not None and p.motion_drop_static_tracks:
        static = static_tracks(tr_sorted.xy, tr_sorted.visible, cams, float(p.motion_threshold_px))
    track_stats = dict(tr_sorted.stats)
    track_stats["flow_seconds"] = round(flow_seconds, 3)
    return _composite_tracks(tr_sorted, order), track_stats, static


def _file_track_stats(tracks: Tracks | None) -> dict[str, Any]:
    """Statistics of tracks read from files (no forward-backward error), {} without tracks."""
    if tracks is None:
        return {}
    track_stats = track_statistics(tracks)
    track_stats.update(fb_error_median_px=-1.0, fb_error_p95_px=-1.0)
    return track_stats


@dataclass
class _InstancePriors:
    mask: np.ndarray | None = None
    ids: np.ndarray | None = None
    names: list[str] | None = None
    rigid: np.ndarray | None = None
    rigid_source: list[str] | None = None
    track_instance: np.ndarray | None = None


def _dataset_instances(scene: Scene) -> _InstancePriors:
    """The dataset's instance masks and instances (ids of the masks where it lists none)."""
    mask = scene.instance_mask.astype(np.int32)
    if scene.instances is not None:
        ids, names, rigid = scene.instances.ids, list(scene.instances.names), scene.instances.rigid
    else:
        found = np.unique(mask)
        ids = found[found > 0].astype(np.int64)
        names = [f"id{i}" for i in ids]
        rigid = -np.ones(len(ids), np.int8)
    return _InstancePriors(mask, ids, names, rigid, ["dataset" if r >= 0 else "unknown" for r in rigid])


def _clustered_instances(
    scene: Scene,
    tracks: Tracks,
    fg: np.ndarray,
    static: np.ndarray | None,
    track_stats: dict[str, Any],
    single_fg: bool,
    p: PriorsSettings,
) -> tuple[_InstancePriors, np.ndarray, Tracks, dict[str, Any]]:
    """Instances from clustering the (moving) tracks, and the foreground, tracks and track
    statistics after leaving the static tracks out (as given where none are known)."""
    moving = np.ones(tracks.num_tracks, bool) if static is None else ~static
    labels = np.zeros(tracks.num_tracks, np.int64)
    labels[moving] = cluster_tracks(tracks.subset(moving), (scene.height, scene.width), p)
    mask = label_pixels(tracks, labels, fg)
    if static is not None:
        # The motion mask bleeds around moving objects: pixels nearest to a
        # static track leave the foreground, static tracks leave the output.
        fg = mask > 0
        tracks = tracks.subset(moving)
        labels = labels[moving]
        kept = {k: track_stats[k] for k in ("flow_seconds", "seconds", "num_query_frames") if k in track_stats}
        track_stats = {**track_statistics(tracks), **kept, "static_tracks_dropped": int((~moving).sum())}
    ids = np.arange(1, int(labels.max(initial=0)) + 1, dtype=np.int64)
    inherited = int(scene.instances.rigid[0]) if single_fg else -1
    inst = _InstancePriors(
        mask=mask,
        ids=ids,
        names=[f"cluster{i}" for i in ids],
        rigid=np.full(len(ids), inherited, np.int8),
        rigid_source=["dataset (inherited from 'foreground')" if inherited >= 0 else "unknown"] * len(ids),
        track_instance=labels,
    )
    return inst, fg, tracks, track_stats


def build_priors(
    scene_h5: str | os.PathLike, split_h5: str | os.PathLike | Split, params: Mapping[str, Any] | None = None
) -> PriorsResult:
    """Priors of the split's observed frames (pure: reads, writes nothing)."""
    t0 = time.perf_counter()
    p = load_settings(params)
    split = split_h5 if isinstance(split_h5, Split) else read_split(split_h5)
    scene = load_frames(scene_h5, split, "observed")
    layout = scene.layout
    iphone = layout == "iphone"
    frame_ids = np.asarray(split.frame_ids["observed"], np.int64)
    timesteps = np.asarray(scene.time_index, np.int64)
    F = scene.num_frames
    shipped = load_observed_shipped(scene_h5, split)
    sources: dict[str, str] = {}

    # Temporal order of the observed frames (the monocular video).
    order = np.argsort(timesteps, kind="stable")
    if iphone and len(np.unique(timesteps)) != F:
        raise MogafError(
            f"{scene_h5}: layout 'iphone' needs one observed frame per time step, "
            f"got {F} frames for {len(np.unique(timesteps))} steps"
        )

    # Depth first: a monocular scene without depth fails before any work.
    depth = depth_valid = None
    depth_kind = "none"
    if iphone:
        depth, depth_valid, depth_kind, sources["depth"] = select_depth(scene_h5, scene, shipped.data, p.depth_sources)
    else:
        sources["depth"] = "none (layout dnerf: multi-view, no depth prior)"

    # Tracks from files, if any (iphone only).
    tracks: Tracks | None = None
    if iphone and p.tracks_source == "auto":
        tracks, tracks_source = _file_tracks(scene_h5, split, shipped.data, timesteps, p)
        if tracks_source is not None:
            sources["tracks"] = tracks_source

    # Foreground masks.
    single_fg = _single_foreground(scene, p)
    fg, masks_source = _given_foreground(scene_h5, scene, shipped.data, single_fg)
    if masks_source is not None:
        sources["masks"] = masks_source

    flows = None
    flow_seconds = 0.0
    frames_sorted = scene.images[order]
    need_flow_tracks = iphone and tracks is None
    if need_flow_tracks or (fg is None and iphone):
        tf = time.perf_counter()
        flows = consecutive_flows(frames_sorted, p)
        flow_seconds = time.perf_counter() - tf
    cams = None  # camera motion per step, when the foreground comes from motion segmentation
    if fg is None:
        fg, cams, sources["masks"] = _derived_foreground(scene, order, flows, p)

    static = None  # computed tracks that do not move beyond the camera (motion-segmented scenes)
    if need_flow_tracks:
        tracks, track_stats, static = _flow_tracks(frames_sorted, fg, order, flows, flow_seconds, cams, p)
        sources["tracks"] = f"optical_flow ({p.flow_method}, forward-backward {p.fb_threshold_px} px)"
    else:
        track_stats = _file_track_stats(tracks)
    if not iphone:
        sources["tracks"] = NO_TRACKS_DNERF

    # Instances.
    have_tracks = tracks is not None and tracks.num_tracks > 0
    if scene.instance_mask is not None and not (single_fg and have_tracks):
        inst = _dataset_instances(scene)
        sources["instances"] = "dataset_instance_masks"
    elif have_tracks:
        inst, fg, tracks, track_stats = _clustered_instances(scene, tracks, fg, static, track_stats, single_fg, p)
        if static is not None:
            sources["masks"] += ", refined by static tracks"
        sources["instances"] = "track_clustering (agglomerative, motion + spatial neighbours)"
    else:
        inst = _InstancePriors()
        sources["instances"] = "none"
    if inst.track_instance is None and have_tracks and inst.mask is not None:
        inst.track_instance = _track_instances(tracks, inst.mask)

    return PriorsResult(
        dataset=scene.dataset,
        scene=scene.name,
        layout=layout,
        ratio=split.ratio,
        frame_ids=frame_ids,
        timesteps=timesteps,
        foreground=fg.astype(np.uint8),
        instance_mask=inst.mask,
        instance_ids=inst.ids,
        instance_names=inst.names,
        instance_rigid=inst.rigid,
        instance_rigid_source=inst.rigid_source,
        depth=depth,
        depth_valid=depth_valid,
        depth_kind=depth_kind,
        tracks=tracks,
        track_instance=inst.track_instance,
        sources=sources,
        track_stats=track_stats,
        shipped_ignored=shipped.ignored,
        seconds=time.perf_counter() - t0,
    )


def _track_instances(tracks: Tracks, inst_mask: np.ndarray) -> np.ndarray:
    """Majority instance id under each track's visible positions (0 = none)."""
    F, H, W = inst_mask.shape
    P = tracks.num_tracks
    out = np.zeros(P, np.int64)
    xs = np.clip(np.floor(tracks.xy[..., 0]).astype(np.int64), 0, W - 1)
    ys = np.clip(np.floor(tracks.xy[..., 1]).astype(np.int64), 0, H - 1)
    ids = inst_mask[np.arange(F)[None, :], ys, xs]  # (P, F)
    ids = np.where(tracks.visible, ids, 0)
    for i in range(P):
        v = ids[i][ids[i] > 0]
        if v.size:
            vals, counts = np.unique(v, return_counts=True)
            out[i] = vals[np.argmax(counts)]
    return out


def write_priors(path: str | os.PathLike, result: PriorsResult, *, config_digest: str) -> Path:
    """Write priors.h5 atomically (stage "priors")."""
    return write_artefact(path, STAGE, result.to_data(), config_digest=config_digest, attrs=result.attrs())


def run_priors_stage(
    scene_h5: str | os.PathLike,
    split_h5: str | os.PathLike,
    out_h5: str | os.PathLike,
    params: Mapping[str, Any] | None = None,
    *,
    digest: str | None = None,
) -> Path:
    """build_priors + write_priors; nothing is written when building fails."""
    result = build_priors(scene_h5, split_h5, params)
    digest = digest or _config_digest({"priors": resolve_params(params)})
    return write_priors(out_h5, result, config_digest=digest)
