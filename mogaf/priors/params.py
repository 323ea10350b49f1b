"""Parameters of the priors stage: the defaults and their checking (resolve_params)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

from ..settings import check, defaults, setting


@dataclass(frozen=True)
class PriorsSettings:
    """Settings of the priors stage (config section `priors`)."""

    # ---- optical flow (computed tracks and motion segmentation)
    flow_method: Literal["dis", "rlof"] = setting(
        "dis", '"dis" (cv2.DISOpticalFlow) or "rlof" (cv2.optflow dense RLOF)'
    )
    dis_preset: Literal["ultrafast", "fast", "medium"] = setting(
        "medium", 'DIS preset: "ultrafast" | "fast" | "medium"'
    )
    dis_finest_scale: int = setting(0, "finest DIS pyramid level (0 = full resolution: slower, the most accurate flow)")
    # ---- chained-flow tracker (mogaf.priors.tracks)
    grid_stride: int = setting(4, "px between query points of the grid", minimum=1)
    num_query_frames: int = setting(8, "evenly spaced query frames (clipped to the number of frames)", minimum=1)
    fb_threshold_px: float = setting(1.0, "forward-backward error a step may have (px) ...")
    fb_relative: float = setting(0.05, "... plus this fraction of the step's flow magnitude")
    photometric_threshold: float = setting(
        0.08, "max mean |RGB change| of the point's patch per step, in [0, 1] (0 disables)"
    )
    photometric_patch_radius: int = setting(2, "patch of (2 r + 1)^2 pixels compared between consecutive frames")
    border_px: float = setting(1.0, "points closer than this to the image border are lost")
    dedup_radius_px: float = setting(4.0, "skip query points this close to an existing visible track (0: keep all)")
    min_track_length: int = setting(5, "drop tracks visible in fewer frames", minimum=1)
    max_tracks: int = setting(20000, "seeded subsample above this many tracks (0: no cap)")
    tracks_source: Literal["auto", "computed"] = setting(
        "auto", '"auto" (shipped -> ground truth -> computed) or "computed"'
    )
    # ---- motion segmentation (foreground when the dataset ships no masks)
    motion_camera_model: Literal["homography", "fundamental", "none"] = setting(
        "homography", 'camera motion removed first: "homography" | "fundamental" | "none"'
    )
    motion_threshold_px: float = setting(0.75, "residual flow (px/frame) that marks a pixel as moving")
    motion_min_area: float = setting(0.002, "components smaller than this fraction of the image are dropped")
    motion_dilate_px: int = setting(2, "dilation of the moving mask (px)")
    motion_drop_static_tracks: bool = setting(
        True, "drop tracks that do not move (px/frame < motion_threshold_px) and their pixels"
    )
    # ---- instances from track clustering (when the dataset ships none; mogaf.priors.instances)
    num_instances: int = setting(0, "groups; 0 = as many as the motion threshold gives, up to max_instances")
    max_instances: int = setting(10, "at most this many groups (the most alike are merged)")
    cluster_motion_threshold_px: float = setting(
        1.0, "groups whose tracks' velocities differ more (px/frame) stay apart"
    )
    cluster_knn: int = setting(10, "spatial neighbours each track may be merged with ...")
    cluster_link_radius_px: float = setting(12.0, "... if their mean distance is at most this (px)")
    cluster_time_stride: int = setting(2, "frames between the positions compared")
    cluster_max_tracks: int = setting(
        1500, "tracks clustered directly (seeded subsample); others join the nearest alike"
    )
    cluster_min_fraction: float = setting(0.02, "smaller groups are merged into the most alike neighbour")
    cluster_single_foreground: bool = setting(
        True, 'a dataset mask whose only instance is "foreground" is split by track clustering'
    )
    # ---- depth (layout iphone)
    depth_sources: list = setting(
        ["shipped", "scene"],
        "order of depth sources (mogaf.priors.depth)",
        schema={
            "anyOf": [
                {"type": "string", "enum": ["shipped", "scene"]},
                {"type": "array", "items": {"type": "string", "enum": ["shipped", "scene"]}},
            ]
        },
    )
    # ---- misc
    seed: int = setting(0, "seeded subsampling (max_tracks, cluster_max_tracks)", injected=True)


DEFAULT_PARAMS: dict[str, Any] = defaults(PriorsSettings)


def resolve_params(params: Mapping[str, Any] | None) -> dict[str, Any]:
    """Defaults overridden by `params`, checked (PriorsSettings); unknown keys are refused (typos)."""
    params = dict(params or {})
    if isinstance(params.get("depth_sources"), str):  # one source may be given as a string
        params["depth_sources"] = [params["depth_sources"]]
    out = check(PriorsSettings, "priors", params)
    out["depth_sources"] = list(out["depth_sources"])
    return out


def load_settings(params: Mapping[str, Any] | PriorsSettings | None) -> PriorsSettings:
    """resolve_params as a frozen PriorsSettings (what the stage's modules read)."""
    if isinstance(params, PriorsSettings):
        return params
    return PriorsSettings(**resolve_params(params))
