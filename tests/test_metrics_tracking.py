"""Tracking metrics against small cases computed by hand."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mogaf.errors import MogafError
from mogaf.metrics import average_jaccard, delta_3d, delta_avg, epe_3d, occlusion_accuracy, tracking_metrics


def _case_3d():
    """3 points, 2 frames; per-(point, frame) errors along x."""
    err = np.array([[0.03, 0.01], [0.08, 9.0], [0.2, 0.06]])
    vis = np.array([[1, 1], [1, 0], [1, 1]], bool)  # the 9.0 error is occluded
    gt = np.zeros((3, 2, 3))
    pred = gt.copy()
    pred[..., 0] = err
    return pred, gt, vis


def test_epe_and_delta_3d_hand_values():
    pred, gt, vis = _case_3d()
    # Frame means 0.31/3 and 0.07/2, then their mean.
    assert epe_3d(pred, gt, vis) == pytest.approx((0.31 / 3 + 0.07 / 2) / 2)
    assert delta_3d(pred, gt, vis, 0.05) == pytest.approx((1 / 3 + 1 / 2) / 2)
    assert delta_3d(pred, gt, vis, 0.10) == pytest.approx((2 / 3 + 2 / 2) / 2)


def test_scale_converts_scene_units():
    pred, gt, vis = _case_3d()
    assert epe_3d(pred, gt, vis, scale=2.0) == pytest.approx(2 * (0.31 / 3 + 0.07 / 2) / 2)
    # Errors become 0.06, 0.16, 0.4 | 0.02, 0.12.
    assert delta_3d(pred, gt, vis, 0.05, scale=2.0) == pytest.approx((0 + 1 / 2) / 2)


def test_delta_3d_is_strict_and_skips_empty_frames():
    gt = np.zeros((2, 3, 3))
    pred = gt.copy()
    pred[0, :, :2] = (3.0, 4.0)  # error exactly 5
    vis = np.array([[1, 1, 0], [1, 1, 0]], bool)  # frame 2 has no visible point
    assert delta_3d(pred, gt, vis, 5.0) == pytest.approx(0.5)
    assert delta_3d(pred, gt, vis, 5.000001) == pytest.approx(1.0)
    assert epe_3d(pred, gt, vis) == pytest.approx(2.5)  # not diluted by the empty frame


def test_all_occluded():
    pred, gt, _ = _case_3d()
    none = np.zeros((3, 2), bool)
    with pytest.raises(MogafError, match="undefined"):
        epe_3d(pred, gt, none)
    with pytest.raises(MogafError, match="undefined"):
        delta_3d(pred, gt, none, 0.1)
    # An always-occluded track (with NaN ground truth) changes nothing.
    p2, g2, v2 = _case_3d()
    p3 = np.concatenate([p2, np.ones((1, 2, 3))])
    g3 = np.concatenate([g2, np.full((1, 2, 3), np.nan)])
    v3 = np.concatenate([v2, np.zeros((1, 2), bool)])
    assert epe_3d(p3, g3, v3) == pytest.approx(epe_3d(p2, g2, v2))
    out = tracking_metrics(
        gt_vis=none, pred_vis=none, pred_3d=pred, gt_3d=gt, pred_2d=pred[..., :2], gt_2d=gt[..., :2], strict=False
    )
    assert out == {
        "epe_3d": None,
        "delta_3d@0.05": None,
        "delta_3d@0.10": None,
        "aj": None,
        "delta_avg": None,
        "occlusion_accuracy": 1.0,
    }
    with pytest.raises(MogafError, match="undefined"):
        tracking_metrics(gt_vis=none, pred_3d=pred, gt_3d=gt)


def _case_2d():
    """Points A, B over 3 frames; offsets with lengths chosen for the thresholds."""
    offsets = np.array(
        [
            [(0.3, 0.4), (3.0, 0.0), (12.0, 16.0)],  # A: 0.5, 3, 20 px
            [(0.0, 0.0), (6.0, 8.0), (0.9, 1.2)],  # B: 0, 10, 1.5 px
        ]
    )
    gt = np.full((2, 3, 2), 50.0)
    pred = gt + offsets
    gt_vis = np.array([[1, 1, 1], [0, 1, 1]], bool)
    pred_vis = np.array([[1, 1, 0], [1, 0, 1]], bool)
    return pred, gt, gt_vis, pred_vis


def test_average_jaccard_hand_value():
    pred, gt, vis, pvis = _case_2d()
    # GP = 5; per threshold (TP, FP): 1:(1,3) 2:(2,2) 4:(3,1) 8:(3,1) 16:(3,1).
    expected = (1 / 8 + 2 / 7 + 3 / 6 + 3 / 6 + 3 / 6) / 5
    assert average_jaccard(pred, gt, vis, pvis) == pytest.approx(expected)
    assert average_jaccard(pred, gt, vis, pvis, thresholds=(4,)) == pytest.approx(0.5)
    # Perfect prediction.
    assert average_jaccard(gt, gt, vis, vis) == pytest.approx(1.0)


def test_delta_avg_hand_values():
    pred, gt, vis, _ = _case_2d()
    # Visible errors 0.5, 3, 20, 10, 1.5 px.
    assert delta_avg(pred, gt, vis) == pytest.approx((3 / 5 + 3 / 5 + 4 / 5 + 1 + 1) / 5)
    assert delta_avg(pred, gt, vis, thresholds=(1, 2, 4, 8, 16)) == pytest.approx((1 + 2 + 3 + 3 + 4) / 25)
    # Strictly within: an error of exactly 3 px does not count at 3 px.
    assert delta_avg(pred, gt, vis, thresholds=(3,)) == pytest.approx(2 / 5)


def test_occlusion_accuracy_and_eval_mask():
    pred, gt, vis, pvis = _case_2d()
    assert occlusion_accuracy(vis, pvis) == pytest.approx(3 / 6)
    only_a = np.array([[1, 1, 1], [0, 0, 0]], bool)
    assert occlusion_accuracy(vis, pvis, eval_mask=only_a) == pytest.approx(2 / 3)
    # On A alone: GP = 3; thresholds 4: TP 2 (0.5, 3), FP 0 -> 2/3.
    assert average_jaccard(pred, gt, vis, pvis, thresholds=(4,), eval_mask=only_a) == pytest.approx(2 / 3)
    with pytest.raises(MogafError, match="undefined"):
        occlusion_accuracy(vis, pvis, eval_mask=np.zeros((2, 3), bool))


def test_tracking_metrics_collects_everything():
    pred, gt, vis, pvis = _case_2d()
    p3, g3, v3 = _case_3d()
    out = tracking_metrics(gt_vis=vis, pred_vis=pvis, pred_2d=pred, gt_2d=gt)
    assert set(out) == {"aj", "delta_avg", "occlusion_accuracy"}
    assert out["delta_avg"] == pytest.approx(0.8)
    out3 = tracking_metrics(gt_vis=v3, pred_3d=torch.from_numpy(p3), gt_3d=g3)
    assert out3["delta_3d@0.05"] == pytest.approx(delta_3d(p3, g3, v3, 0.05))
    assert set(out3) == {"epe_3d", "delta_3d@0.05", "delta_3d@0.10"}


def test_malformed_inputs():
    pred, gt, vis, pvis = _case_2d()
    with pytest.raises(MogafError, match="shape"):
        delta_avg(pred[:, :2], gt, vis)
    with pytest.raises(MogafError, match="0/1"):
        occlusion_accuracy(vis, pvis * 0.5)
    with pytest.raises(MogafError, match="non-finite"):
        delta_avg(np.full_like(pred, np.nan), gt, vis)
    with pytest.raises(MogafError, match="thresholds"):
        delta_avg(pred, gt, vis, thresholds=())
    with pytest.raises(MogafError, match="pred_vis"):
        average_jaccard(pred, gt, vis, None)
    with pytest.raises(MogafError, match="both"):
        tracking_metrics(gt_vis=vis, pred_2d=pred)


def test_still_points_and_how_far_a_forecast_moves_them():
    """Ground-truth points that never move (observed and forecast steps), and
    the mean distance of their carried positions from where they rest: 0 for
    a forecast that leaves them, the shift for one that moves them."""
    from mogaf.evaluate.tracking import STILL_TOLERANCE, still_points, still_points_displacement

    rng = np.random.default_rng(0)
    rest = rng.normal(size=(6, 3))
    observed = np.repeat(rest[:, None], 5, axis=1)
    future = np.repeat(rest[:, None], 3, axis=1)
    observed[0, 1] += 0.01  # moved while observed, back at the last step
    future[1, 2] += 0.02  # moves after the split
    observed[2, 3, 0] += 0.5 * STILL_TOLERANCE  # within the tolerance
    future[3, 0] = np.nan  # no position: not still
    assert still_points(observed, future).tolist() == [False, False, True, False, True, True]
    assert still_points(observed).tolist() == [False, True, True, True, True, True]
    pred = future.copy()
    pred[3] = rest[3]
    assert still_points_displacement(np.nan_to_num(pred), observed, future) == {
        "still_points": 3,
        "still_points_displacement": pytest.approx(0.0, abs=1e-15),
    }
    moved = pred + np.array([0.0, 0.03, 0.04])
    assert still_points_displacement(moved, observed, future)["still_points_displacement"] == pytest.approx(0.05)
    assert still_points_displacement(moved, observed + 1.0, future) == {"still_points": 0}
