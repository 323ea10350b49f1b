"""DyCheck iPhone layout (+ Shape-of-Motion's preprocessing) -> Scene.

DyCheck files read (S = options["scale"], default 2):
  splits/train.json, splits/val.json   frame_names, camera_ids, time_ids
                                       (val optional)
  camera/<name>.json                   orientation (w2c rotation), position
                                       (camera centre), focal_length,
                                       principal_point, pixel_aspect_ratio
                                       (fy = fx * ratio), skew, image_size
                                       [W, H] at full resolution,
                                       radial/tangential_distortion
  dataset.json, metadata.json          optional cross-checks (ids, count,
                                       camera_id, warp_id = time index)
  scene.json, extra.json               optional; kept in meta
  rgb/<S>x/<name>.png                  RGB or RGBA; A is DyCheck's valid-pixel
                                       mask -> Scene.alpha (colours are NOT
                                       composited)
  depth/<S>x/<name>.npy                optional (H, W[, 1]) projective depth
                                       (0 = invalid) -> Scene.depth; frames
                                       without a file (held-out) get 0
  covisible/<S>x/val/<name>.png        optional -> Scene.covisible (1 where
                                       covisible; training frames are all 1)
  keypoint/<S>x/train/<name>.json      optional (J, 3) [x, y, visible]; when
                                       only keypoint/2x exists it is rescaled
  points.npy                           optional (N, 3) background points ->
                                       point_cloud (grey: no colours)

Shape-of-Motion files read (under flow3d_preprocessed/):
  track_anything/<S>x/<name>.png       foreground masks (SoM reads value/255
                                       and thresholds at 0.5) -> instance_mask
                                       with one instance "foreground" (id 1)
  aligned_<som_depth>/<S>x/<name>.npy  disparity (SoM inverts it to depth),
                                       som_depth default depth_anything_colmap
  colmap/scale.npy                     for a som_depth ending in _colmap: SoM's
                                       COLMAP-to-camera-json length factor; the
                                       disparity is divided by it (required)
  2d_tracks/<S>x/<q>_<t>.npy           (P, 4) TAPIR tracks of the points
                                       queried in train frame q, seen in
                                       train frame t: x, y, occlusion logit,
                                       expected-distance logit
  covisible/<S>x/val/<name>.png        used when DyCheck's covisible/ is absent

Stored in Scene.shipped (frames are rows of the scene, in its order):
  disparity: frame (N,), time_index (N,), values (N, H, W) float32
  keypoints: frame (N,), time_index (N,), values (N, J, 3) float32
             [x, y, visible] in continuous pixel coordinates (centres +0.5)
  tracks_2d: query_frame (Q,), query_time_index (Q,), target_frame (M,),
             target_time_index (M,), offsets (Q+1,) int64, values
             (offsets[-1], M, 4) float32: the points of query q are rows
             offsets[q]:offsets[q+1]; x, y converted to the +0.5 pixel-centre
             convention (SoM/TAPIR put pixel centres at integers)
  distortion (only when some camera has non-zero distortion):
             frame (N,), radial (N, 3), tangential (N, 2)

Decisions: the world is NOT rescaled (camera jsons as they are; DyCheck's
center/scale/near/far go to meta, near/far being in DyCheck's normalised
units); distortion is recorded and a warning issued, images are not
undistorted (the DyCheck iPhone captures have zero distortion); frame order is
train then val, as listed; time_index = time_ids, num_timesteps = max + 1 over
both splits, time = time_index / (num_timesteps - 1).

Options: scale (2), depth (true), priors (true: SoM files), som_depth,
tracks (true), tracks_query_stride (1), tracks_max_points (256; 0 = all),
rigidity (patterns for "foreground"), workers.

Modules: metadata (splits, camera and scene JSON, keypoints), loaders
(.npy arrays, 2D tracks, points, binary masks, the frame-loading thread
pool), reader (read_iphone_layout).
"""

from .reader import DistortionWarning, missing_message, read_iphone_layout

__all__ = ["DistortionWarning", "missing_message", "read_iphone_layout"]
