"""3D and 2D point-tracking metrics on forecast frames.

The protocol follows Shape-of-Motion's evaluation (`scripts/evaluate_iphone.py`
in vye16/shape-of-motion, Wang et al. 2024), which MoGaF's tracking table
uses, and TAP-Vid (Doersch et al. 2022) for the 2D definitions.

Inputs (numpy arrays or torch tensors)
    ``pred_3d``, ``gt_3d``: (P, T, 3) positions of P points over T frames;
    ``pred_2d``, ``gt_2d``: (P, T, 2) pixel positions (x, y);
    ``gt_vis``: (P, T) ground-truth visibility (True = visible);
    ``pred_vis``: (P, T) predicted visibility;
    ``eval_mask``: optional (P, T), the (point, frame) pairs to evaluate
    (default: all). Shape-of-Motion excludes the query frame itself and, for
    each query frame, the points not visible in it; on forecast frames the
    query frames are observed ones, so the default is normally right.
    Visibility arrays may be boolean or 0/1 numbers. Ground-truth positions
    may be NaN where they are not evaluated (not visible or masked out).

Units
    3D errors are ``scale * ||pred - gt||``. Shape-of-Motion measures them in
    metres: the iPhone scenes' COLMAP reconstruction is multiplied by the
    dataset's metric scale factor (``scale.npy``) and the prediction is
    aligned to it by a similarity (Procrustes) fit of the camera centres, so
    its thresholds 0.05 and 0.10 mean 5 cm and 10 cm. Pass positions already
    aligned, and ``scale`` converting their units to metres (1 if they are in
    metres). 2D thresholds are in pixels of the coordinates given;
    Shape-of-Motion uses full-resolution (1x) iPhone pixels, whereas TAP-Vid
    first rescales to 256x256, so rescale beforehand if that is wanted.

All ratios are fractions in [0, 1] (the paper prints them as percentages).
A metric with nothing to average (e.g. every point occluded in every frame)
raises `MogafError` naming the metric; `tracking_metrics(strict=False)`
reports such metrics as None instead.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mogaf.errors import MogafError

__all__ = [
    "DEFAULT_3D_THRESHOLDS",
    "DEFAULT_AJ_THRESHOLDS",
    "DEFAULT_PCK_THRESHOLDS",
    "epe_3d",
    "delta_3d",
    "average_jaccard",
    "delta_avg",
    "occlusion_accuracy",
    "tracking_metrics",
]

DEFAULT_3D_THRESHOLDS = (0.05, 0.10)
DEFAULT_AJ_THRESHOLDS = (1, 2, 4, 8, 16)  # TAP-Vid
# The delta_avg set (Shape-of-Motion's); TAP-Vid uses (1, 2, 4, 8, 16).
DEFAULT_PCK_THRESHOLDS = (4, 8, 16, 32, 64)


def _numpy(x, what: str) -> np.ndarray:
    if hasattr(x, "detach") and hasattr(x, "cpu"):
        x = x.detach().cpu().numpy()
    arr = np.asarray(x)
    if arr.dtype == object:
        raise MogafError(f"{what}: expected a numeric array, got {type(x).__name__}")
    return arr


def _points(x, what: str, dim: int) -> np.ndarray:
    arr = _numpy(x, what)
    if arr.ndim != 3 or arr.shape[-1] != dim:
        raise MogafError(f"{what}: expected shape (P, T, {dim}), got {tuple(arr.shape)}")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise MogafError(f"{what}: expected numbers, got dtype {arr.dtype}")
    return arr.astype(np.float64)


def _flags(x, what: str, shape: tuple[int, int]) -> np.ndarray:
    arr = _numpy(x, what)
    if tuple(arr.shape) != tuple(shape):
        raise MogafError(f"{what}: expected shape {tuple(shape)}, got {tuple(arr.shape)}")
    if arr.dtype == np.bool_:
        return arr
    if not (np.issubdtype(arr.dtype, np.number)) or not np.isin(arr, (0, 1)).all():
        raise MogafError(f"{what}: expected booleans or 0/1 values")
    return arr != 0


def _thresholds(values: Sequence[float], what: str) -> tuple[float, ...]:
    out = tuple(float(v) for v in values)
    if not out or any(not np.isfinite(v) or v <= 0 for v in out):
        raise MogafError(f"{what}: expected a non-empty list of positive thresholds, got {list(values)}")
    return out


def _eval(eval_mask, shape) -> np.ndarray:
    return np.ones(shape, dtype=bool) if eval_mask is None else _flags(eval_mask, "eval_mask", shape)


def _check_finite(arr: np.ndarray, where: np.ndarray, what: str) -> None:
    if not np.isfinite(arr[where]).all():
        raise MogafError(f"{what}: non-finite positions at evaluated points")


def _errors_3d(pred_3d, gt_3d, gt_vis, eval_mask, scale) -> tuple[np.ndarray, np.ndarray]:
    pred = _points(pred_3d, "pred_3d", 3)
    gt = _points(gt_3d, "gt_3d", 3)
    if pred.shape != gt.shape:
        raise MogafError(f"pred_3d and gt_3d differ in shape: {pred.shape} vs {gt.shape}")
    if not np.isfinite(scale) or scale <= 0:
        raise MogafError(f"scale must be a positive number, got {scale}")
    shape = pred.shape[:2]
    valid = _flags(gt_vis, "gt_vis", shape) & _eval(eval_mask, shape)
    _check_finite(pred, valid, "pred_3d")
    _check_finite(gt, valid, "gt_3d")
    err = np.zeros(shape)
    err[valid] = scale * np.linalg.norm(pred[valid] - gt[valid], axis=-1)
    return err, valid


def _per_frame_mean(values: np.ndarray, valid: np.ndarray, metric: str) -> float:
    """Mean over frames (with >= 1 valid point) of the per-frame mean over valid points."""
    counts = valid.sum(axis=0)
    frames = counts > 0
    if not frames.any():
        raise MogafError(f"{metric} is undefined: no ground-truth-visible point in any evaluated frame")
    sums = np.where(valid, values, 0.0).sum(axis=0)
    return float(np.mean(sums[frames] / counts[frames]))


def epe_3d(pred_3d, gt_3d, gt_vis, *, eval_mask=None, scale: float = 1.0) -> float:
    """3D end-point error, Shape-of-Motion style.

    For every frame t the error ``scale * ||pred[p, t] - gt[p, t]||`` is
    averaged over the points p that are ground-truth visible (and in
    ``eval_mask``); EPE is the mean of these per-frame means over the frames
    that have at least one such point (frames without any are skipped).
    """
    err, valid = _errors_3d(pred_3d, gt_3d, gt_vis, eval_mask, scale)
    return _per_frame_mean(err, valid, "3D EPE")


def delta_3d(pred_3d, gt_3d, gt_vis, threshold: float, *, eval_mask=None, scale: float = 1.0) -> float:
    """delta_3D at ``threshold``: share of points with ``scale * error < threshold``.

    Strict inequality; per-frame fractions over the ground-truth-visible points,
    then averaged over frames that have any (as `epe_3d`). With ``scale`` mapping
    to metres, 0.05 and 0.10 are Shape-of-Motion's 5 cm and 10 cm PCK.
    """
    (t,) = _thresholds([threshold], "threshold")
    err, valid = _errors_3d(pred_3d, gt_3d, gt_vis, eval_mask, scale)
    return _per_frame_mean((err < t).astype(np.float64), valid, f"delta_3D@{threshold:g}")


def _tracks_2d(pred_2d, gt_2d, gt_vis, pred_vis, eval_mask):
    pred = _points(pred_2d, "pred_2d", 2)
    gt = _points(gt_2d, "gt_2d", 2)
    if pred.shape != gt.shape:
        raise MogafError(f"pred_2d and gt_2d differ in shape: {pred.shape} vs {gt.shape}")
    shape = pred.shape[:2]
    vis = _flags(gt_vis, "gt_vis", shape)
    pvis = None if pred_vis is None else _flags(pred_vis, "pred_vis", shape)
    ev = _eval(eval_mask, shape)
    used = ev & (vis if pvis is None else (vis | pvis))
    _check_finite(pred, used, "pred_2d")
    _check_finite(gt, ev & vis, "gt_2d")
    sq = np.full(shape, np.inf)
    sq[used] = np.sum((pred[used] - gt[used]) ** 2, axis=-1)
    return sq, vis, pvis, ev


def delta_avg(pred_2d, gt_2d, gt_vis, *, thresholds=DEFAULT_PCK_THRESHOLDS, eval_mask=None) -> float:
    """delta^x_avg: position accuracy averaged over pixel thresholds.

    For each threshold d: the share of evaluated, ground-truth-visible
    (point, frame) pairs whose prediction lies strictly within d pixels
    (``||pred - gt||^2 < d^2``), pooled over all points and frames as TAP-Vid
    pools within a video; then the mean over thresholds. Predicted visibility
    plays no part. The default {4, 8, 16, 32, 64} is the issue's (and
    Shape-of-Motion's) set; TAP-Vid's is {1, 2, 4, 8, 16}.
    """
    ths = _thresholds(thresholds, "thresholds")
    sq, vis, _, ev = _tracks_2d(pred_2d, gt_2d, gt_vis, None, eval_mask)
    denom = int(np.sum(vis & ev))
    if denom == 0:
        raise MogafError("delta_avg is undefined: no ground-truth-visible evaluated point")
    return float(np.mean([np.sum((sq < d * d) & vis & ev) / denom for d in ths]))


def average_jaccard(pred_2d, gt_2d, gt_vis, pred_vis, *, thresholds=DEFAULT_AJ_THRESHOLDS, eval_mask=None) -> float:
    """Average Jaccard (TAP-Vid), pooled over the evaluated (point, frame) pairs.

    For each threshold d, with ``within = ||pred - gt||^2 < d^2``:

    * true positives  TP = #(gt visible and pred visible and within),
    * false positives FP = #(pred visible and (gt occluded or not within)),
    * ground-truth positives GP = #(gt visible),

    Jaccard_d = TP / (GP + FP) (missed visible points count through GP);
    AJ is the mean over thresholds, default {1, 2, 4, 8, 16} px as TAP-Vid.
    Undefined (raises) when no evaluated point is ground-truth visible.
    """
    ths = _thresholds(thresholds, "thresholds")
    if pred_vis is None:
        raise MogafError("average_jaccard needs pred_vis (predicted visibility)")
    sq, vis, pvis, ev = _tracks_2d(pred_2d, gt_2d, gt_vis, pred_vis, eval_mask)
    gp = int(np.sum(vis & ev))
    if gp == 0:
        raise MogafError("AJ is undefined: no ground-truth-visible evaluated point")
    scores = []
    for d in ths:
        within = sq < d * d
        tp = np.sum(within & vis & pvis & ev)
        fp = np.sum(pvis & (~vis | ~within) & ev)
        scores.append(tp / (gp + fp))
    return float(np.mean(scores))


def occlusion_accuracy(gt_vis, pred_vis, *, eval_mask=None) -> float:
    """Share of evaluated (point, frame) pairs whose predicted visibility equals the ground truth."""
    vis = _numpy(gt_vis, "gt_vis")
    if vis.ndim != 2:
        raise MogafError(f"gt_vis: expected shape (P, T), got {tuple(vis.shape)}")
    shape = vis.shape
    vis = _flags(vis, "gt_vis", shape)
    pvis = _flags(pred_vis, "pred_vis", shape)
    ev = _eval(eval_mask, shape)
    n = int(ev.sum())
    if n == 0:
        raise MogafError("occlusion accuracy is undefined: no evaluated point")
    return float(np.sum((vis == pvis) & ev) / n)


def tracking_metrics(
    *,
    gt_vis,
    pred_vis=None,
    pred_3d=None,
    gt_3d=None,
    pred_2d=None,
    gt_2d=None,
    eval_mask=None,
    scale: float = 1.0,
    thresholds_3d: Sequence[float] = DEFAULT_3D_THRESHOLDS,
    aj_thresholds: Sequence[float] = DEFAULT_AJ_THRESHOLDS,
    pck_thresholds: Sequence[float] = DEFAULT_PCK_THRESHOLDS,
    strict: bool = True,
) -> dict[str, float | None]:
    """All tracking metrics the given inputs allow, as a flat dict.

    Keys: ``epe_3d`` and ``delta_3d@<t>`` (one per ``thresholds_3d``, e.g.
    ``delta_3d@0.05``) when 3D tracks are given; ``delta_avg``, plus ``aj``
    when ``pred_vis`` is given, for 2D tracks; ``occlusion_accuracy`` when
    ``pred_vis`` is given. With ``strict=False`` an undefined metric is None
    (JSON null) instead of an error; malformed inputs always raise.
    """

    def run(fn, *args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except MogafError as exc:
            if strict or "undefined" not in str(exc):
                raise
            return None

    out: dict[str, float | None] = {}
    if (pred_3d is None) != (gt_3d is None):
        raise MogafError("3D tracking needs both pred_3d and gt_3d")
    if (pred_2d is None) != (gt_2d is None):
        raise MogafError("2D tracking needs both pred_2d and gt_2d")
    if pred_3d is not None:
        out["epe_3d"] = run(epe_3d, pred_3d, gt_3d, gt_vis, eval_mask=eval_mask, scale=scale)
        for t in thresholds_3d:
            key = f"{float(t):.2f}" if round(float(t), 2) == float(t) else f"{float(t):g}"
            out[f"delta_3d@{key}"] = run(delta_3d, pred_3d, gt_3d, gt_vis, t, eval_mask=eval_mask, scale=scale)
    if pred_2d is not None:
        if pred_vis is not None:
            out["aj"] = run(
                average_jaccard, pred_2d, gt_2d, gt_vis, pred_vis, thresholds=aj_thresholds, eval_mask=eval_mask
            )
        out["delta_avg"] = run(delta_avg, pred_2d, gt_2d, gt_vis, thresholds=pck_thresholds, eval_mask=eval_mask)
    if pred_vis is not None:
        out["occlusion_accuracy"] = run(occlusion_accuracy, gt_vis, pred_vis, eval_mask=eval_mask)
    return out
