"""Training data of the reconstruction stage: observed frames + priors.

Only `mogaf.split.load_frames(scene_h5, split, "observed")` is read from
scene.h5 (the observed rows), so nothing of the future can leak in. Images,
masks, depth and tracks are downscaled here by an integer factor (area
average; intrinsics scaled exactly, see mogaf.camera).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..artefact import ATTR_DIGEST, ATTR_LINEAGE, read_artefact, read_attrs
from ..camera import scale_intrinsics
from ..errors import input_error
from ..split import Split, load_frames, read_split


@dataclass
class TrainData:
    images: np.ndarray  # (F, H, W, 3) float32 in [0, 1]
    fg_masks: np.ndarray  # (F, H, W) float32 in [0, 1]
    K: np.ndarray  # (F, 3, 3) float64 (at training resolution)
    w2c: np.ndarray  # (F, 4, 4) float64
    tidx: np.ndarray  # (F,) int64: position of the frame's time step in `timesteps`
    timesteps: np.ndarray  # (T,) scene time-grid indices of the observed steps
    frame_ids: np.ndarray  # (F,) rows of scene.h5
    layout: str
    background: np.ndarray  # (3,) float32
    depth: np.ndarray | None = None  # (F, H, W) float32 metric depth (0 where invalid)
    depth_valid: np.ndarray | None = None  # (F, H, W) bool
    tracks_xy: np.ndarray | None = None  # (P, F, 2) float32, pixels (+0.5 convention)
    tracks_visible: np.ndarray | None = None  # (P, F) bool
    tracks_query: np.ndarray | None = None  # (P,) int64 frame index (into F)
    point_cloud: np.ndarray | None = None  # (P, 6) xyz rgb, dataset-level
    instance_mask: np.ndarray | None = None  # (F, H, W) int32, 0 = background
    content_offset: int = 0  # > 0: labels above it are "content next to instance (label - offset)"
    downscale: int = 1

    @property
    def num_frames(self) -> int:
        return int(self.images.shape[0])

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    @property
    def num_timesteps(self) -> int:
        return int(self.timesteps.shape[0])

    @property
    def has_depth(self) -> bool:
        return self.depth is not None

    @property
    def has_tracks(self) -> bool:
        return self.tracks_xy is not None and self.tracks_xy.shape[0] > 0


def _area_down(x: np.ndarray, s: int) -> np.ndarray:
    """Area-average (F, H, W, ...) by an integer factor (crops the remainder)."""
    if s == 1:
        return x
    F, H, W = x.shape[:3]
    h, w = H // s, W // s
    x = x[:, : h * s, : w * s]
    shape = (F, h, s, w, s) + x.shape[3:]
    return x.reshape(shape).mean(axis=(2, 4))


def downscale_depth(depth: np.ndarray, valid: np.ndarray, s: int) -> tuple[np.ndarray, np.ndarray]:
    """Block mean of the valid depths; a block is valid if any pixel is."""
    if s == 1:
        return depth, valid
    v = valid.astype(np.float64)
    num = _area_down(depth * v, s)
    den = _area_down(v, s)
    out_valid = den > 0
    out = np.where(out_valid, num / np.maximum(den, 1e-12), 0.0)
    return out.astype(np.float32), out_valid


def load_train_data(
    scene_h5: str | os.PathLike,
    split: Split | str | os.PathLike,
    priors_h5: str | os.PathLike | None,
    *,
    downscale: int = 1,
) -> TrainData:
    sp = split if isinstance(split, Split) else read_split(split)
    scene = load_frames(scene_h5, sp, "observed")
    ids = np.asarray(sp.frame_ids["observed"], dtype=np.int64)
    s = int(downscale)
    H, W = scene.height, scene.width
    if H // s < 8 or W // s < 8:
        raise input_error(scene_h5, f"downscale {s} leaves an image smaller than 8x8 ({W}x{H})")
    steps = np.asarray(sp.observed_timesteps, dtype=np.int64)
    pos = {int(t): i for i, t in enumerate(steps)}
    bad = [int(t) for t in scene.time_index if int(t) not in pos]
    if bad:
        raise input_error(scene_h5, f"observed frame at time step {bad[0]} outside the observed steps")
    tidx = np.array([pos[int(t)] for t in scene.time_index], dtype=np.int64)

    images = _area_down(scene.images.astype(np.float32) / 255.0, s).astype(np.float32)
    K = scale_intrinsics(scene.K, 1.0 / s)
    bg = np.asarray(scene.meta.get("background", (1.0, 1.0, 1.0)), dtype=np.float32).reshape(-1)[:3]
    if bg.size != 3:
        bg = np.ones(3, np.float32)

    fg = None
    inst = None
    depth = valid = None
    tracks_xy = tracks_vis = tracks_q = None
    if priors_h5 is not None:
        pr = read_artefact(priors_h5, "priors", required=["frame_ids", "masks/foreground"])
        pids = np.asarray(pr["frame_ids"], dtype=np.int64)
        where = {int(f): i for i, f in enumerate(pids)}
        missing = [int(f) for f in ids if int(f) not in where]
        if missing:
            raise input_error(priors_h5, f"has no priors for observed frame {missing[0]} of scene.h5")
        order = np.array([where[int(f)] for f in ids], dtype=np.int64)
        masks = np.asarray(pr["masks/foreground"])[order]
        if masks.shape[1:] != (H, W):
            raise input_error(priors_h5, f"foreground masks are {masks.shape[1:]}, images are {(H, W)}")
        fg = _area_down((masks > 0).astype(np.float32), s)
        if "masks/instance" in pr:
            im = np.asarray(pr["masks/instance"], dtype=np.int32)[order]
            inst = im[:, s // 2 :: s, s // 2 :: s][:, : H // s, : W // s] if s > 1 else im
        if "depth/values" in pr:
            d = np.asarray(pr["depth/values"], dtype=np.float64)[order]
            v = np.asarray(pr["depth/valid"]).astype(bool)[order] if "depth/valid" in pr else np.ones_like(d, bool)
            kind = str(pr.attrs.get("depth_kind", "depth"))
            v &= d > 0
            if kind == "disparity":
                d = np.where(v, 1.0 / np.maximum(d, 1e-12), 0.0)
            depth, valid = downscale_depth(np.where(v, d, 0.0), v, s)
        if "tracks/xy" in pr:
            xy = np.asarray(pr["tracks/xy"], dtype=np.float32)[:, order]
            vis = np.asarray(pr["tracks/visible"]).astype(bool)[:, order]
            q = np.asarray(pr["tracks/query_index"], dtype=np.int64)
            # query_index is a row of the priors' frame list; map to ours
            inv = np.full(len(pids), -1, np.int64)
            inv[order] = np.arange(len(order))
            q = inv[np.clip(q, 0, len(pids) - 1)]
            tracks_xy = xy / s
            tracks_vis = vis
            tracks_q = q
    if fg is None:
        if scene.alpha is not None:
            fg = _area_down((scene.alpha > 127).astype(np.float32), s)
        elif scene.instance_mask is not None:
            fg = _area_down((scene.instance_mask > 0).astype(np.float32), s)
        else:
            fg = np.ones(images.shape[:3], np.float32)

    return TrainData(
        images=images,
        fg_masks=fg.astype(np.float32),
        K=K,
        w2c=np.asarray(scene.w2c, dtype=np.float64),
        tidx=tidx,
        timesteps=steps,
        frame_ids=ids,
        layout=scene.layout,
        background=bg,
        depth=depth,
        depth_valid=valid,
        tracks_xy=tracks_xy,
        tracks_visible=tracks_vis,
        tracks_query=tracks_q,
        point_cloud=scene.point_cloud,
        instance_mask=inst,
        downscale=s,
    )


def input_digests(paths: dict[str, Any]) -> dict[str, str]:
    """Lineage digests of the input artefacts (settings and contents), for the
    checkpoint digest: a checkpoint made from inputs since rewritten with
    other values is not resumed. Config digests for files without lineage."""
    out = {}
    for name, p in paths.items():
        if p is None:
            continue
        attrs = read_attrs(Path(p))
        out[name] = str(attrs.get(ATTR_LINEAGE) or attrs.get(ATTR_DIGEST, ""))
    return out


def extend_masks_to_content(data: TrainData, tau: float) -> float:
    """Without a background model every visible thing must be a dynamic Gaussian.

    The foreground masks are widened to every pixel that differs from the
    background colour by more than `tau` (any channel): cast shadows, mask
    edges lost to anti-aliasing, unlabelled objects. Such pixels get the
    label (offset + id of the nearest labelled pixel), offset = the largest
    instance id: "content next to instance k" (its shadow, typically) is its
    own group, free to move differently from k. Returns the fraction of
    pixels added.
    """
    from scipy.ndimage import binary_opening, distance_transform_edt

    added = 0
    total = 0
    offset = int(data.instance_mask.max()) if data.instance_mask is not None else 1
    if data.instance_mask is not None:
        data.content_offset = offset
    for f in range(data.num_frames):
        diff = np.abs(data.images[f] - data.background[None, None]).max(-1) > tau
        diff = binary_opening(diff, iterations=1) | (data.fg_masks[f] > 0.5)
        extra = diff & (data.fg_masks[f] <= 0.5)
        added += int(extra.sum())
        total += extra.size
        if not extra.any():
            continue
        data.fg_masks[f] = np.maximum(data.fg_masks[f], diff.astype(np.float32))
        if data.instance_mask is not None:
            lab = data.instance_mask[f]
            if (lab > 0).any():
                _, (ri, ci) = distance_transform_edt(lab == 0, return_indices=True)
                data.instance_mask[f] = np.where(extra, lab[ri, ci] + offset, lab)
    return added / max(total, 1)


def coarser(data: TrainData, factor: int) -> TrainData:
    """The same frames at 1/factor resolution (area average; labels and tracks follow)."""
    import dataclasses

    s = int(factor)
    if s <= 1:
        return data
    H, W = data.height // s, data.width // s
    depth = valid = None
    if data.has_depth:
        depth, valid = downscale_depth(data.depth, data.depth_valid, s)
    inst = None
    if data.instance_mask is not None:
        inst = data.instance_mask[:, s // 2 :: s, s // 2 :: s][:, :H, :W]
    return dataclasses.replace(
        data,
        images=_area_down(data.images, s).astype(np.float32),
        fg_masks=_area_down(data.fg_masks, s).astype(np.float32),
        K=scale_intrinsics(data.K, 1.0 / s),
        depth=depth,
        depth_valid=valid,
        tracks_xy=None if data.tracks_xy is None else (data.tracks_xy / s).astype(np.float32),
        instance_mask=inst,
        downscale=data.downscale * s,
    )
