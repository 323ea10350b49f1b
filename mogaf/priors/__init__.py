"""Priors stage: results/{dataset}/{scene}/ratio{r}/priors.h5.

Masks, instance identities, depth and 2D tracks of the split's *observed*
frames. Everything is computed from those frames only (scene rows read
through mogaf.split.load_frames, shipped priors and ground truth cut to the
observed time steps while reading, see mogaf.priors.shipped): a tracker or
segmenter that saw future frames would leak the answer.

Sources (first that applies; the one used is recorded in attrs["sources"]):
- foreground: dataset instance masks (> 0; the iPhone reader stores SoM's
  track_anything masks there) -> shipped/foreground -> alpha (when not all opaque) -> layout "dnerf": pixels
  unlike the background colour, else the whole frame -> layout "iphone":
  motion segmentation of the optical flow (mogaf.priors.masks), refined by
  the tracks: tracks that do not move beyond the camera motion are dropped
  and the pixels nearest to them leave the mask (`motion_drop_static_tracks`).
- instances: dataset instance masks with the scene's rigidity flags (set at
  ingest from the dataset or the config's rigidity rules) -> layout
  "iphone": clustering of the 2D tracks by motion among spatial neighbours,
  pixels labelled by the nearest track (mogaf.priors.instances), rigidity unknown (-1). A
  dataset mask whose single instance is named "foreground" (Shape-of-Motion's
  track_anything mask, as the iPhone reader stores it) is only a foreground
  mask: it is split by clustering (`cluster_single_foreground`), the clusters
  inheriting its rigidity flag when that is known.
- depth (layout "iphone" only): see mogaf.priors.depth; a monocular scene
  without any fails with one line naming the files to provide.
- tracks (layout "iphone" only): shipped 2D tracks (e.g. SoM's) -> the
  synthetic scene's ground-truth tracks (train camera 0) -> chained optical
  flow (mogaf.priors.tracks). Layout "dnerf" gets no tracks: its camera
  teleports between views (every frame is its own camera), so the flow
  between consecutive frames mixes camera jumps with motion and is
  meaningless. No depth either: D-NeRF-style scenes are multi-view.

priors.h5 (stage "priors"):
  frame_ids (F_o,) int64            rows of scene.h5 = the split's observed frames, same order
  timesteps (F_o,) int64            their time indices (observed steps)
  masks/foreground (F_o,H,W) uint8  {0,1}
  masks/instance (F_o,H,W) int32    0 = background; only when instance ids exist
  instances/ids (K,) int64, instances/names [K str], instances/rigid (K,) int8 (1/0/-1),
  instances/rigid_source [K str]    "dataset" (scene.h5 flag, set at ingest from the dataset or
                                    the config's rigidity rules), "dataset (inherited from
                                    'foreground')", "unknown"
  instances/num_pixels (K,) int64   foreground pixels per instance over the observed frames
  depth/values (F_o,H,W) float32, depth/valid (F_o,H,W) uint8     layout iphone only
  tracks/query_index (P,) int64     observed-frame index where the point was queried
  tracks/xy (P,F_o,2) float32       pixel coordinates, pixel centres at i + 0.5;
                                    invisible steps hold the last known position
  tracks/visible (P,F_o) uint8
  tracks/confidence (P,F_o) float32 in [0, 1], 0 where invisible
  tracks/fb_error (P,F_o) float32   forward-backward error (px) of the step reaching
                                    each frame (computed tracks only)
  tracks/instance (P,) int64        instance id of each track (0 = none), when instances exist
  attrs: dataset, scene, layout, ratio, num_observed_frames, sources (JSON mapping
    masks/instances/depth/tracks -> source), depth_kind ("depth" | "disparity" | "none"),
    track_count, track_mean_length, track_fb_error_median_px, track_fb_error_p95_px
    (-1 when the tracks were not computed here) and the other numeric track
    statistics as track_<name> (visible_fraction, fb_error_steps, num_frames,
    num_query_frames, flow_seconds, seconds, static_tracks_dropped), seconds,
    shipped_ignored (JSON list of shipped entries not read).
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.special import expit

from ..artefact import config_digest as _config_digest
from ..artefact import write_artefact
from ..errors import MogafError, refuse_unknown_params
from ..split import Split, load_frames, read_split

STAGE = "priors"

DEFAULT_PARAMS: dict[str, Any] = {
    # ---- optical flow (computed tracks and motion segmentation)
    "flow_method": "dis",  # "dis" (cv2.DISOpticalFlow) or "rlof" (cv2.optflow dense RLOF)
    "dis_preset": "medium",  # DIS preset: "ultrafast" | "fast" | "medium"
    "dis_finest_scale": 0,  # finest DIS pyramid level (0 = full resolution: ~3x slower, ~2x more accurate)
    # ---- chained-flow tracker (mogaf.priors.tracks)
    "grid_stride": 4,  # px between query points of the grid
    "num_query_frames": 8,  # evenly spaced query frames (clipped to the number of frames)
    "fb_threshold_px": 1.0,  # forward-backward error a step may have (px) ...
    "fb_relative": 0.05,  # ... plus this fraction of the step's flow magnitude
    "photometric_threshold": 0.08,  # max mean |RGB change| of the point's patch per step, in [0, 1] (0 disables)
    "photometric_patch_radius": 2,  # patch of (2 r + 1)^2 pixels compared between consecutive frames
    "border_px": 1.0,  # points closer than this to the image border are lost
    "dedup_radius_px": 4.0,  # skip query points this close to an existing visible track (0: keep all)
    "min_track_length": 5,  # drop tracks visible in fewer frames
    "max_tracks": 20000,  # seeded subsample above this many tracks (0: no cap)
    "tracks_source": "auto",  # "auto" (shipped -> ground truth -> computed) or "computed"
    # ---- motion segmentation (foreground when the dataset ships no masks)
    "motion_camera_model": "homography",  # camera motion removed first: "homography" | "fundamental" | "none"
    "motion_threshold_px": 0.75,  # residual flow (px/frame) that marks a pixel as moving
    "motion_min_area": 0.002,  # components smaller than this fraction of the image are dropped
    "motion_dilate_px": 2,  # dilation of the moving mask (px)
    "motion_drop_static_tracks": True,  # drop tracks that do not move (px/frame < motion_threshold_px) and their pixels
    # ---- instances from track clustering (when the dataset ships none; mogaf.priors.instances)
    "num_instances": 0,  # groups; 0 = as many as the motion threshold gives, up to max_instances
    "max_instances": 10,  # at most this many groups (the most alike are merged)
    "cluster_motion_threshold_px": 1.0,  # groups whose tracks' velocities differ more (px/frame) stay apart
    "cluster_knn": 10,  # spatial neighbours each track may be merged with ...
    "cluster_link_radius_px": 12.0,  # ... if their mean distance is at most this (px)
    "cluster_time_stride": 2,  # frames between the positions compared
    "cluster_max_tracks": 1500,  # tracks clustered directly (seeded subsample); others join the nearest alike
    "cluster_min_fraction": 0.02,  # smaller groups are merged into the most alike neighbour
    "cluster_single_foreground": True,  # a dataset mask whose only instance is "foreground" is split by track clustering
    # ---- depth (layout iphone)
    "depth_sources": ["shipped", "scene"],  # order of depth sources (mogaf.priors.depth)
    # ---- misc
    "seed": 0,  # seeded subsampling (max_tracks, cluster_max_tracks)
}

from .depth import select_depth  # noqa: E402
from .flow import consecutive_flows  # noqa: E402
from .instances import cluster_tracks, label_pixels  # noqa: E402
from .masks import background_colour_mask, motion_segmentation, static_tracks  # noqa: E402
from .shipped import load_observed_ground_truth_tracks, load_observed_shipped  # noqa: E402
from .tracks import Tracks, compute_flow_tracks, track_statistics  # noqa: E402

__all__ = [
    "DEFAULT_PARAMS",
    "PriorsResult",
    "Tracks",
    "build_priors",
    "compute_flow_tracks",
    "resolve_params",
    "run_priors_stage",
    "write_priors",
]

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
            data["depth"] = {"values": np.asarray(self.depth, np.float32), "valid": np.asarray(self.depth_valid, np.uint8)}
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


def resolve_params(params: Mapping[str, Any] | None) -> dict[str, Any]:
    """Defaults overridden by `params`; unknown keys are refused (typos)."""
    params = dict(params or {})
    refuse_unknown_params("priors", params, DEFAULT_PARAMS)
    out = {**DEFAULT_PARAMS, **params}
    if out["tracks_source"] not in ("auto", "computed"):
        raise MogafError(f"priors: tracks_source must be 'auto' or 'computed', got {out['tracks_source']!r}")
    if isinstance(out["depth_sources"], str):
        out["depth_sources"] = [out["depth_sources"]]
    out["depth_sources"] = list(out["depth_sources"])
    for key in ("grid_stride", "min_track_length", "num_query_frames"):
        if int(out[key]) < 1:
            raise MogafError(f"priors: {key} must be >= 1, got {out[key]!r}")
    return out


# ---------------------------------------------------------------- helpers
def _shipped_foreground(shipped: Mapping[str, Any]) -> np.ndarray | None:
    entry = shipped.get("foreground")
    if isinstance(entry, Mapping) and "values" in entry:
        arr = np.asarray(entry["values"])
        if arr.ndim == 4:
            arr = arr[..., 0]
        return arr > 0
    return None


def _finish_tracks(xy: np.ndarray, vis: np.ndarray, conf: np.ndarray | None, query_index: np.ndarray | None,
                   p: Mapping[str, Any]) -> Tracks:
    """Tracks over the observed frames from file data: fill, filter, cap."""
    P, F = vis.shape
    keep = vis.sum(1) >= int(p["min_track_length"])
    if query_index is None:
        query_index = np.where(vis.any(1), vis.argmax(1), 0).astype(np.int64)
    xy = _fill_invisible(np.asarray(xy, np.float32), vis)
    conf = vis.astype(np.float32) if conf is None else np.asarray(conf, np.float32)
    conf = np.where(vis, np.clip(conf, 0.0, 1.0), 0.0).astype(np.float32)
    tr = Tracks(query_index=np.asarray(query_index, np.int64), xy=xy, visible=vis, confidence=conf, fb_error=None).subset(keep)
    cap = int(p["max_tracks"])
    if cap > 0 and tr.num_tracks > cap:
        rng = np.random.default_rng(int(p["seed"]))
        tr = tr.subset(np.sort(rng.choice(tr.num_tracks, cap, replace=False)))
    return tr


def _fill_invisible(xy: np.ndarray, vis: np.ndarray) -> np.ndarray:
    P, F = vis.shape
    out = np.where(np.isfinite(xy), xy, 0.0).astype(np.float32)
    if P == 0 or F == 0:
        return out
    idx = np.where(vis, np.arange(F)[None], -1)
    last = np.maximum.accumulate(idx, axis=1)  # last visible frame at or before t
    first = np.where(vis.any(1), vis.argmax(1), 0)
    src = np.where(last >= 0, last, first[:, None])
    return np.take_along_axis(out, src[..., None].repeat(2, -1), axis=1)


def _shipped_tracks(shipped: Mapping[str, Any], p) -> Tracks | None:
    """Shape-of-Motion/TAPIR tracks: visible where (1 - sigmoid(occlusion)) *
    (1 - sigmoid(expected_dist)) > 0.5, as SoM reads them; confidence =
    1 - sigmoid(expected_dist)."""
    g = shipped.get("tracks_2d")
    if not isinstance(g, Mapping) or "xy" not in g:
        return None
    visibility = expit(-np.asarray(g["occlusion"], np.float64))
    certainty = expit(-np.asarray(g["expected_dist"], np.float64))
    vis = visibility * certainty > 0.5
    # The query frame itself is visible by definition.
    P = vis.shape[0]
    vis[np.arange(P), g["query_index"]] = True
    return _finish_tracks(g["xy"], vis, certainty, g["query_index"], p)


def _ground_truth_tracks(gt: Mapping[str, Any], split: Split, timesteps: np.ndarray, p) -> Tracks | None:
    """Synthetic ground truth (P, T_obs) over observed steps -> observed frames."""
    if "tracks2d" not in gt:
        return None
    cols = np.searchsorted(split.observed_timesteps, timesteps)
    xy = np.asarray(gt["tracks2d"], np.float32)[:, cols]
    vis = gt.get("visible")
    vis = np.ones(xy.shape[:2], bool) if vis is None else (np.asarray(vis) > 0)[:, cols]
    return _finish_tracks(xy, vis, None, None, p)


def _composite_tracks(tr: Tracks, order: np.ndarray) -> Tracks:
    """Tracks over frames in temporal order -> columns in the split's order."""
    F = len(order)
    inv = np.empty(F, np.int64)
    inv[order] = np.arange(F)
    # column order[k] of the output is column k of the sorted tracks
    out = Tracks(
        query_index=order[tr.query_index] if tr.num_tracks else tr.query_index,
        xy=tr.xy[:, inv],
        visible=tr.visible[:, inv],
        confidence=tr.confidence[:, inv],
        fb_error=None if tr.fb_error is None else tr.fb_error[:, inv],
        stats=tr.stats,
    )
    return out


# ---------------------------------------------------------------- the stage
def build_priors(scene_h5: str | os.PathLike, split_h5: str | os.PathLike | Split, params: Mapping[str, Any] | None = None) -> PriorsResult:
    """Priors of the split's observed frames (pure: reads, writes nothing)."""
    t0 = time.perf_counter()
    p = resolve_params(params)
    split = split_h5 if isinstance(split_h5, Split) else read_split(split_h5)
    scene = load_frames(scene_h5, split, "observed")
    layout = scene.layout
    frame_ids = np.asarray(split.frame_ids["observed"], np.int64)
    timesteps = np.asarray(scene.time_index, np.int64)
    F, H, W = scene.num_frames, scene.height, scene.width
    shipped = load_observed_shipped(scene_h5, split)
    sources: dict[str, str] = {}

    # Temporal order of the observed frames (the monocular video).
    order = np.argsort(timesteps, kind="stable")
    if layout == "iphone" and len(np.unique(timesteps)) != F:
        raise MogafError(f"{scene_h5}: layout 'iphone' needs one observed frame per time step, "
                         f"got {F} frames for {len(np.unique(timesteps))} steps")

    # Depth first: a monocular scene without depth fails before any work.
    depth = depth_valid = None
    depth_kind = "none"
    if layout == "iphone":
        depth, depth_valid, depth_kind, sources["depth"] = select_depth(scene_h5, scene, shipped.data, p["depth_sources"])
    else:
        sources["depth"] = "none (layout dnerf: multi-view, no depth prior)"

    # Tracks from files, if any (iphone only).
    tracks: Tracks | None = None
    if layout == "iphone" and p["tracks_source"] == "auto":
        tracks = _shipped_tracks(shipped.data, p)
        if tracks is not None:
            sources["tracks"] = "shipped"
        else:
            gt = load_observed_ground_truth_tracks(scene_h5, split)
            tracks = _ground_truth_tracks(gt, split, timesteps, p)
            if tracks is not None:
                sources["tracks"] = "ground_truth"

    # Foreground masks.
    fg = None
    # A dataset "instance" mask with the single instance "foreground" (the
    # iPhone reader's Shape-of-Motion track_anything mask) is a foreground
    # mask: instances then come from clustering the tracks inside it.
    single_fg = bool(
        p["cluster_single_foreground"] and layout == "iphone" and scene.instance_mask is not None
        and scene.instances is not None and len(scene.instances.ids) == 1
        and scene.instances.names[0].lower() == "foreground"
    )
    if scene.instance_mask is not None:
        fg = scene.instance_mask > 0
        sources["masks"] = "dataset_foreground_mask" if single_fg else "dataset_instance_masks"
    elif _shipped_foreground(shipped.data) is not None:
        fg, sources["masks"] = _shipped_foreground(shipped.data), "shipped_masks"
        if fg.shape != (F, H, W):
            raise MogafError(f"{scene_h5}: shipped masks have shape {fg.shape}, expected {(F, H, W)}")
    elif scene.alpha is not None and np.any(scene.alpha < 255):
        fg, sources["masks"] = scene.alpha >= 128, "alpha"

    flows = None
    flow_seconds = 0.0
    frames_sorted = scene.images[order]
    need_flow_tracks = layout == "iphone" and tracks is None
    if need_flow_tracks or (fg is None and layout == "iphone"):
        tf = time.perf_counter()
        flows = consecutive_flows(frames_sorted, p)
        flow_seconds = time.perf_counter() - tf
    cams = None  # camera motion per step, when the foreground comes from motion segmentation
    if fg is None:
        if layout == "iphone":
            fg_sorted, cams = motion_segmentation(*flows, p)
            fg = np.empty_like(fg_sorted)
            fg[order] = fg_sorted
            sources["masks"] = f"motion_segmentation ({p['flow_method']} flow, {p['motion_camera_model']} camera)"
        elif scene.meta.get("background") is not None:
            fg, sources["masks"] = background_colour_mask(scene.images, scene.meta["background"]), "background_colour"
        else:
            fg, sources["masks"] = np.ones((F, H, W), bool), "none (whole frame)"

    static = None  # computed tracks that do not move beyond the camera (motion-segmented scenes)
    if need_flow_tracks:
        tr_sorted = compute_flow_tracks(frames_sorted, fg[order], p, flows=flows)
        if cams is not None and p["motion_drop_static_tracks"]:
            static = static_tracks(tr_sorted.xy, tr_sorted.visible, cams, float(p["motion_threshold_px"]))
        tracks = _composite_tracks(tr_sorted, order)
        sources["tracks"] = f"optical_flow ({p['flow_method']}, forward-backward {p['fb_threshold_px']} px)"
        track_stats = dict(tr_sorted.stats)
        track_stats["flow_seconds"] = round(flow_seconds, 3)
    elif tracks is not None:
        track_stats = track_statistics(tracks)
        track_stats.update(fb_error_median_px=-1.0, fb_error_p95_px=-1.0)
    else:
        track_stats = {}
    if layout != "iphone":
        sources["tracks"] = NO_TRACKS_DNERF

    # Instances.
    inst_mask = inst_ids = inst_names = inst_rigid = inst_src = None
    track_instance = None
    have_tracks = tracks is not None and tracks.num_tracks > 0
    if scene.instance_mask is not None and not (single_fg and have_tracks):
        inst_mask = scene.instance_mask.astype(np.int32)
        if scene.instances is not None:
            inst_ids, inst_names, inst_rigid = scene.instances.ids, list(scene.instances.names), scene.instances.rigid
        else:
            ids = np.unique(inst_mask)
            inst_ids = ids[ids > 0].astype(np.int64)
            inst_names = [f"id{i}" for i in inst_ids]
            inst_rigid = -np.ones(len(inst_ids), np.int8)
        inst_src = ["dataset" if r >= 0 else "unknown" for r in inst_rigid]
        sources["instances"] = "dataset_instance_masks"
    elif have_tracks:
        moving = np.ones(tracks.num_tracks, bool) if static is None else ~static
        labels = np.zeros(tracks.num_tracks, np.int64)
        labels[moving] = cluster_tracks(tracks.subset(moving), (H, W), p)
        inst_mask = label_pixels(tracks, labels, fg)
        if static is not None:
            # The motion mask bleeds around moving objects: pixels nearest to a
            # static track leave the foreground, static tracks leave the output.
            fg = inst_mask > 0
            tracks = tracks.subset(moving)
            labels = labels[moving]
            kept = {k: track_stats[k] for k in ("flow_seconds", "seconds", "num_query_frames") if k in track_stats}
            track_stats = {**track_statistics(tracks), **kept, "static_tracks_dropped": int((~moving).sum())}
            sources["masks"] += ", refined by static tracks"
        track_instance = labels
        inst_ids = np.arange(1, int(track_instance.max(initial=0)) + 1, dtype=np.int64)
        inst_names = [f"cluster{i}" for i in inst_ids]
        inherited = int(scene.instances.rigid[0]) if single_fg else -1
        inst_rigid = np.full(len(inst_ids), inherited, np.int8)
        inst_src = ["dataset (inherited from 'foreground')" if inherited >= 0 else "unknown"] * len(inst_ids)
        sources["instances"] = "track_clustering (agglomerative, motion + spatial neighbours)"
    else:
        sources["instances"] = "none"
    if track_instance is None and have_tracks and inst_mask is not None:
        track_instance = _track_instances(tracks, inst_mask)

    return PriorsResult(
        dataset=scene.dataset,
        scene=scene.name,
        layout=layout,
        ratio=split.ratio,
        frame_ids=frame_ids,
        timesteps=timesteps,
        foreground=fg.astype(np.uint8),
        instance_mask=inst_mask,
        instance_ids=inst_ids,
        instance_names=inst_names,
        instance_rigid=inst_rigid,
        instance_rigid_source=inst_src,
        depth=depth,
        depth_valid=depth_valid,
        depth_kind=depth_kind,
        tracks=tracks,
        track_instance=track_instance,
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


def run_priors_stage(scene_h5: str | os.PathLike, split_h5: str | os.PathLike, out_h5: str | os.PathLike,
                     params: Mapping[str, Any] | None = None, *, digest: str | None = None) -> Path:
    """build_priors + write_priors; nothing is written when building fails."""
    result = build_priors(scene_h5, split_h5, params)
    digest = digest or _config_digest({"priors": resolve_params(params)})
    return write_priors(out_h5, result, config_digest=digest)
