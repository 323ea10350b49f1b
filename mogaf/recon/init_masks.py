"""Initialisation without tracks: foreground masks (and depth when there is some).

Scenes without depth (D-NeRF layout): candidates are drawn along the rays of
the canonical frame's fg pixels inside the volume (the dataset point cloud's
bounding box if any, else that of the camera centres) and kept if they fall
in the (dilated) fg masks of most frames within a few time steps of the
canonical one (a short-window visual hull); bases start at identity and
coefficients come from k-means on the canonical positions. Optional bg:
points of the volume that project outside every fg mask.

With depth but no tracks, the canonical frame's fg pixels with valid depth
are lifted instead. When `silhouette_fit_iters` > 0 the bases are then fitted
to the masks (mogaf.recon.silhouette) and, with `hull_min_fraction` > 0, the
points are carved again with that motion.
"""

from __future__ import annotations

import numpy as np
import torch

from ..camera import camera_centers
from ..errors import MogafError
from .data import TrainData
from .init_common import (
    IDENTITY_6D,
    InitResult,
    _bg_from_depth,
    _dilate,
    _use_bg,
    _volume_box,
    coef_logits_from_centres,
    gaussian_tensors,
    knn_scale,
    pixel_labels,
    project,
    robust_extent,
    sample_pixels,
    unproject,
)
from .silhouette import carve_with_motion, fit_bases_to_silhouettes


def _window_frames(data: TrainData, cano: int, half: int) -> np.ndarray:
    dt = np.abs(data.tidx - data.tidx[cano])
    sel = np.flatnonzero(dt <= half)
    if sel.size < 4:
        sel = np.argsort(dt, kind="stable")[: min(4, data.num_frames)]
    return sel


def carve_points(
    data: TrainData, cano: int, params: dict, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points on the rays of the canonical frame's fg pixels that stay in nearby frames' fg masks.

    Returns points (M,3), colours (M,3) and instance labels (M,).
    """
    lo, hi = _volume_box(data)
    fgm = data.fg_masks[cano] > 0.5
    rr, cc = np.nonzero(fgm)
    if rr.size == 0:
        raise MogafError("reconstruction init: the canonical frame has no foreground pixel")
    n_cand = params.carve_candidates
    pix = rng.integers(0, rr.size, size=n_cand)
    uv = np.stack([cc[pix] + rng.random(n_cand), rr[pix] + rng.random(n_cand)], axis=1)
    K, w2c = data.K[cano], data.w2c[cano]
    dirs_cam = np.concatenate([uv, np.ones((n_cand, 1))], axis=1) @ np.linalg.inv(K).T
    R, t = w2c[:3, :3], w2c[:3, 3]
    origin = -R.T @ t
    dirs = dirs_cam @ R  # world, z-depth units
    # ray / box intersection in z-depth units
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (lo[None] - origin[None]) / dirs
        t1 = (hi[None] - origin[None]) / dirs
    tmin = np.nanmax(np.minimum(t0, t1), axis=1)
    tmax = np.nanmin(np.maximum(t0, t1), axis=1)
    tmin = np.maximum(tmin, 1e-3)
    hit = tmax > tmin
    z = tmin + rng.random(n_cand) * (tmax - tmin)
    pts = origin[None] + dirs * z[:, None]
    pts, pix = pts[hit], pix[hit]
    frames = [f for f in _window_frames(data, cano, params.carve_window) if f != cano]
    votes = np.zeros(pts.shape[0])
    seen = np.zeros(pts.shape[0])
    lab_img = data.instance_mask if data.instance_mask is not None else (data.fg_masks > 0.5).astype(np.int64)
    n_lab = int(lab_img.max()) + 1
    label_votes = np.zeros((pts.shape[0], n_lab))
    label_votes[np.arange(pts.shape[0]), pixel_labels(data, cano, rr[pix], cc[pix])] += 1.0
    for f in frames:
        m = _dilate(data.fg_masks[f] > 0.5, params.carve_dilate)
        uvf, zf = project(pts, data.K[f], data.w2c[f])
        inside = (zf > 0) & (uvf[:, 0] >= 0) & (uvf[:, 1] >= 0) & (uvf[:, 0] < data.width) & (uvf[:, 1] < data.height)
        seen += inside
        uvs = np.where(inside[:, None], uvf, 0.0)
        votes += inside & sample_pixels(m, uvs)
        lab = sample_pixels(lab_img[f], uvs)
        np.add.at(label_votes, (np.flatnonzero(inside), lab[inside]), 1.0)
    frac = votes / np.maximum(seen, 1)
    keep = (seen > 0) & (frac >= params.carve_min_fraction)
    if keep.sum() < 64:  # too strict for this motion: keep the best-supported half
        keep = frac >= np.quantile(frac, 0.5)
    colours = data.images[cano][rr[pix[keep]], cc[pix[keep]]]
    # a point behind the first surface of the canonical ray may belong to another instance:
    # majority label over the canonical and window frames (background votes ignored)
    label_votes[:, 0] = 0
    labels = np.argmax(label_votes[keep], axis=1).astype(np.int64)
    none = label_votes[keep].max(axis=1) <= 0
    labels[none] = pixel_labels(data, cano, rr[pix[keep]], cc[pix[keep]])[none]
    return pts[keep], colours, labels


def instance_aware_coefs(
    points: np.ndarray, labels: np.ndarray, num_bases: int, scale: float, length: float, seed: int
) -> np.ndarray:
    """Coefficient logits from k-means centres; centres never straddle instances.

    Bases are shared out among the instances in proportion to their points
    (at least one each, while there are enough bases); a point's logits are
    scale * (1 + exp(-d / length)) for the centres of its own instance and 0
    for the others (plain k-means + distance when there are more instances
    than bases or no labels).
    """
    from sklearn.cluster import KMeans

    ids, counts = np.unique(labels, return_counts=True)
    B = max(1, min(num_bases, points.shape[0]))
    if len(ids) <= 1 or len(ids) > B:
        km = KMeans(n_clusters=B, n_init=3, random_state=seed).fit(points)
        return coef_logits_from_centres(points, km.cluster_centers_, scale, length)
    share = np.ones(len(ids), np.int64)
    extra = B - len(ids)
    if extra > 0:
        want = counts / counts.sum() * B
        for _ in range(extra):
            share[int(np.argmax(want - share))] += 1
    logits = np.zeros((points.shape[0], int(share.sum())), np.float32)
    col = 0
    for i, k in enumerate(ids):
        sel = labels == k
        n = int(min(share[i], sel.sum()))
        km = KMeans(n_clusters=n, n_init=3, random_state=seed).fit(points[sel])
        d = np.linalg.norm(points[sel][:, None] - km.cluster_centers_[None], axis=-1)
        logits[np.ix_(np.flatnonzero(sel), np.arange(col, col + n))] = scale * (1 + np.exp(-d / max(length, 1e-9)))
        col += n
    return logits[:, :col]


def occlusion_contacts(data: TrainData, f: int) -> int:
    """Pixels where two different objects' masks touch (4-neighbours) in frame f: a proxy for occlusion."""
    if data.instance_mask is None:
        return 0
    lab = data.instance_mask[f]
    off = data.content_offset
    base = np.where((lab > off) & (off > 0), lab - off, lab)
    n = 0
    for a, b in ((base[1:], base[:-1]), (base[:, 1:], base[:, :-1])):
        n += int(((a > 0) & (b > 0) & (a != b)).sum())
    return n


def rank_canonical_frames(data: TrainData) -> np.ndarray:
    """Without tracks: a frame of the middle half of the sequence where every instance is seen, none
    touches the image border, and the objects overlap little. Score = fg area / (1 + contacts /
    (sqrt(area) / 2)), contacts = pixels where two objects' masks meet (see occlusion_contacts); a
    carve from an occluded view mislabels the points behind the occluder."""
    t = data.tidx
    lo, hi = np.quantile(t, 0.25), np.quantile(t, 0.75)
    cands = np.flatnonzero((t >= lo) & (t <= hi))
    area = np.array([(data.fg_masks[f] > 0.5).sum() for f in cands], dtype=np.float64)
    border = np.array(
        [bool((data.fg_masks[f][[0, -1]] > 0.5).any() or (data.fg_masks[f][:, [0, -1]] > 0.5).any()) for f in cands]
    )
    if data.instance_mask is not None:
        ids = np.unique(data.instance_mask)
        ids = ids[ids != 0]
        complete = np.array([np.isin(ids, np.unique(data.instance_mask[f])).all() for f in cands])
    else:
        complete = np.ones(len(cands), bool)
    contacts = np.array([occlusion_contacts(data, f) for f in cands], dtype=np.float64)
    quality = area / (1.0 + contacts / np.maximum(np.sqrt(area) / 2, 1.0))
    score = quality * (~border) * complete
    if score.max() <= 0:
        score = quality * complete if (quality * complete).max() > 0 else area
    return cands[np.argsort(-score, kind="stable")]


def _carved(data: TrainData, cano: int, params: dict, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng([seed, 7, cano])
    pts, cols, labels = carve_points(data, cano, params, rng)
    if pts.shape[0] > params.num_fg_init:
        sel = np.sort(rng.choice(pts.shape[0], params.num_fg_init, replace=False))
        pts, cols, labels = pts[sel], cols[sel], labels[sel]
    return pts, cols, labels


def _carve_and_fit(data: TrainData, cano: int, params: dict, seed: int, iters: int) -> float:
    """Residual (px, forward + coverage) of a short silhouette fit from canonical frame `cano`."""
    pts, _, labels = _carved(data, cano, params, seed)
    fg_extent = robust_extent(pts)
    logits = instance_aware_coefs(
        pts, labels, params.num_bases, params.init_coef_scale, params.init_coef_length * 2 * fg_extent, seed
    )
    B, T = logits.shape[1], data.num_timesteps
    rot = IDENTITY_6D.reshape(1, 1, 6).repeat(B, T, 1)
    tr = torch.zeros(B, T, 3)
    _, _, info = fit_bases_to_silhouettes(
        data,
        pts,
        logits,
        labels,
        rot,
        tr,
        cano,
        _scale_without_depth(data, pts, fg_extent),
        iters=max(iters, 1),
        max_points=params.silhouette_fit_points,
        frames_per_iter=params.silhouette_fit_frames,
        pool=params.silhouette_pixels,
        seed=seed,
        w_still=params.silhouette_fit_still,
        w_smooth=params.silhouette_fit_smooth,
        smoothness=params.smooth_bases,
        gap_fill=params.gap_interpolation,
    )
    return float(info["silhouette_fit_forward_px"] + info["silhouette_fit_coverage_px"])


def _scale_without_depth(data: TrainData, pts: np.ndarray, fg_extent: float) -> float:
    # the objects move: their extent at one time says little; use the volume (or the camera distance)
    if data.point_cloud is not None and len(data.point_cloud) >= 8:
        lo, hi = _volume_box(data)
        scale = float(np.max(hi - lo) / 2)
    else:
        dist = np.linalg.norm(camera_centers(data.w2c) - pts.mean(0), axis=1)
        scale = float(0.25 * np.median(dist))
    return max(scale, fg_extent)


def _init_without_tracks(data: TrainData, params: dict, rng: np.random.Generator, seed: int) -> InitResult:
    T = data.num_timesteps
    if data.has_depth:
        # monocular with depth but no tracks: the canonical frame's fg pixels
        counts = [(data.fg_masks[f] > 0.5).sum() for f in range(data.num_frames)]
        cano = int(np.argmax(counts))
        m = (data.fg_masks[cano] > 0.5) & data.depth_valid[cano]
        rr, cc = np.nonzero(m)
        if rr.size == 0:
            raise MogafError("reconstruction init: no foreground pixel with valid depth")
        sel = np.sort(rng.choice(rr.size, min(params.num_fg_init, rr.size), replace=False))
        uv = np.stack([cc[sel] + 0.5, rr[sel] + 0.5], axis=1)
        pts = unproject(uv, data.depth[cano][rr[sel], cc[sel]], data.K[cano], data.w2c[cano])
        cols = data.images[cano][rr[sel], cc[sel]]
        labels = pixel_labels(data, cano, rr[sel], cc[sel])
    else:
        if params.canonical_frame >= 0:
            cano = params.canonical_frame
        else:
            ranked = rank_canonical_frames(data)[: max(1, params.canonical_candidates)]
            cano = int(ranked[0])
            if len(ranked) > 1 and params.silhouette_fit_iters > 0 and data.num_timesteps > 1:
                # the best-scored frame is not always the best start: keep the one whose short
                # silhouette fit leaves the smallest residual
                trials = []
                for c in ranked:
                    r = _carve_and_fit(data, int(c), params, seed, params.silhouette_fit_iters // 4)
                    trials.append(r)
                cano = int(ranked[int(np.argmin(trials))])
        pts, cols, labels = _carved(data, cano, params, seed)
    fg_extent = robust_extent(pts)
    logits = instance_aware_coefs(
        pts, labels, params.num_bases, params.init_coef_scale, params.init_coef_length * 2 * fg_extent, seed
    )
    B = logits.shape[1]
    fg = gaussian_tensors(pts, cols, rng, params.init_opacity, params.sh_degree, True, logits)
    fg["labels"] = torch.tensor(labels, dtype=torch.int64)
    rot = IDENTITY_6D.reshape(1, 1, 6).repeat(B, T, 1)
    tr = torch.zeros(B, T, 3)
    bg = None
    bg_pts = np.zeros((0, 3))
    if _use_bg(params, data):
        if data.has_depth:
            bg_pts, bg_cols = _bg_from_depth(data, params.num_bg_init, rng)
        else:
            bg_pts, bg_cols = _bg_outside_masks(data, params.num_bg_init, rng)
        if bg_pts.shape[0] >= 4:
            bg = gaussian_tensors(bg_pts, bg_cols, rng, params.init_opacity, params.sh_degree, False)
    if bg_pts.shape[0]:
        scene_scale = robust_extent(np.concatenate([pts, bg_pts]))
    elif data.has_depth:
        scene_scale = fg_extent
    else:
        scene_scale = _scale_without_depth(data, pts, fg_extent)
    info = {"canonical_frame": cano, "fg_extent": fg_extent, "num_clusters": B}
    source = "identity"
    if params.silhouette_fit_iters > 0 and data.num_timesteps > 1:
        rot, tr, sinfo = fit_bases_to_silhouettes(
            data,
            pts,
            logits,
            labels,
            rot,
            tr,
            cano,
            scene_scale,
            iters=params.silhouette_fit_iters,
            max_points=params.silhouette_fit_points,
            frames_per_iter=params.silhouette_fit_frames,
            pool=params.silhouette_pixels,
            seed=seed,
            w_still=params.silhouette_fit_still,
            w_smooth=params.silhouette_fit_smooth,
            smoothness=params.smooth_bases,
            gap_fill=params.gap_interpolation,
        )
        info.update(sinfo)
        source = "silhouette"
        if params.hull_min_fraction > 0:
            keep = carve_with_motion(
                data, pts, logits, rot, tr, dilate=params.carve_dilate, min_fraction=params.hull_min_fraction
            )
            info["hull_kept_fraction"] = float(keep.mean())
            if keep.sum() >= 32:
                pts, cols, labels, logits = pts[keep], cols[keep], labels[keep], logits[keep]
                # refill the budget with jittered copies of the survivors
                n_more = params.num_fg_init - pts.shape[0]
                if n_more > 0:
                    src = rng.integers(0, pts.shape[0], size=n_more)
                    jitter = rng.normal(size=(n_more, 3)) * knn_scale(pts, 3)[src, None] * 0.5
                    pts = np.concatenate([pts, pts[src] + jitter])
                    cols, labels, logits = (
                        np.concatenate([cols, cols[src]]),
                        np.concatenate([labels, labels[src]]),
                        np.concatenate([logits, logits[src]]),
                    )
                fg = gaussian_tensors(pts, cols, rng, params.init_opacity, params.sh_degree, True, logits)
                fg["labels"] = torch.tensor(labels, dtype=torch.int64)
    return InitResult(fg, rot, tr, bg, scene_scale, cano, source, info)


def _bg_outside_masks(data: TrainData, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Volume points never inside a (dilated) fg mask of a frame that sees them."""
    lo, hi = _volume_box(data)
    cand = lo + rng.random((max(4 * n, 1000), 3)) * (hi - lo)
    ok = np.ones(cand.shape[0], bool)
    seen = np.zeros(cand.shape[0])
    col = np.zeros((cand.shape[0], 3))
    step = max(1, data.num_frames // 32)
    for f in range(0, data.num_frames, step):
        m = _dilate(data.fg_masks[f] > 0.5, 2)
        uv, z = project(cand, data.K[f], data.w2c[f])
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < data.width) & (uv[:, 1] < data.height)
        uvs = np.where(inside[:, None], uv, 0.0)
        ok &= ~(inside & sample_pixels(m, uvs))
        seen += inside
        col += inside[:, None] * sample_pixels(data.images[f], uvs)
    keep = ok & (seen > 0)
    P, C = cand[keep], col[keep] / np.maximum(seen[keep, None], 1)
    if P.shape[0] > n:
        sel = np.sort(rng.choice(P.shape[0], n, replace=False))
        P, C = P[sel], C[sel]
    return P, C
