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

Modules: params (DEFAULT_PARAMS, resolve_params), stage (build_priors,
write_priors, run_priors_stage), file_tracks (tracks read from files),
depth, flow, instances, masks, shipped, tracks.
"""

from .params import DEFAULT_PARAMS, resolve_params

__all__ = ["DEFAULT_PARAMS", "resolve_params"]
