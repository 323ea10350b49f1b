"""The chained-flow tracker, motion clustering and the carphone smoke test."""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from mogaf.priors import DEFAULT_PARAMS
from mogaf.priors.instances import cluster_tracks, label_pixels
from mogaf.priors.tracks import compute_flow_tracks
from support.moving_squares import moving_squares
from support.paths import shared_path


@pytest.mark.parametrize("method, tol", [("dis", (0.15, 0.5, 0.1)), ("rlof", (0.4, 2.0, 0.2))])
def test_tracker_follows_subpixel_translation_and_loses_occluded_points(method, tol):
    rng = np.random.default_rng(1)
    T, H, W = 16, 96, 128
    x0, y0, vx, vy, size = 30.0, 28.0, 0.6, 0.35, 40
    frames, alphas, occ = moving_squares(rng, T, H, W, [(x0, y0, vx, vy, size)], occluder=(W + 2.0, -8.0, 4))
    fg = (alphas[0] > 0.99) & (occ < 0.01)  # query points on the square only
    params = {**DEFAULT_PARAMS, "grid_stride": 4, "num_query_frames": 3, "flow_method": method}
    tr = compute_flow_tracks(frames, fg, params)
    assert tr.num_tracks > 30
    assert tr.xy.shape == (tr.num_tracks, T, 2) and np.all(np.isfinite(tr.xy))
    # Ground truth: the point moves with the square from its query position.
    t = np.arange(T)[None, :]
    q = tr.query_index[:, None]
    gt = tr.xy[np.arange(tr.num_tracks), tr.query_index][:, None, :] + (t - q)[..., None] * np.array([vx, vy])
    err = np.linalg.norm(tr.xy - gt, axis=-1)
    # Points away from the square's edge and from the occluder.
    interior = np.ones_like(tr.visible)
    for ti in range(T):
        a = cv2.erode((alphas[0, ti] > 0.99).astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
        o = cv2.dilate((occ[ti] > 0.01).astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
        xi = np.clip(gt[:, ti, 0].astype(int), 0, W - 1)
        yi = np.clip(gt[:, ti, 1].astype(int), 0, H - 1)
        interior[:, ti] = a[yi, xi] & ~o[yi, xi]
    good = tr.visible & interior
    assert good.sum() > 200
    assert np.median(err[good]) < tol[0]
    assert np.percentile(err[good], 95) < tol[1]
    # Points whose true position is under the occluder are not visible.
    covered = np.zeros_like(tr.visible)
    for ti in range(T):
        xi = np.clip(np.round(gt[:, ti, 0] - 0.5).astype(int), 0, W - 1)
        yi = np.clip(np.round(gt[:, ti, 1] - 0.5).astype(int), 0, H - 1)
        covered[:, ti] = occ[ti][yi, xi] > 0.99
    assert covered.sum() > 50
    assert tr.visible[covered].mean() < tol[2]
    # Statistics of the forward-backward check are reported.
    assert tr.stats["count"] == tr.num_tracks
    assert 0 <= tr.stats["fb_error_median_px"] <= tr.stats["fb_error_p95_px"] < DEFAULT_PARAMS["fb_threshold_px"] * 2
    assert np.all((tr.confidence >= 0) & (tr.confidence <= 1)) and np.all(tr.confidence[~tr.visible] == 0)


def test_tracks_are_clustered_into_two_differently_moving_objects():
    rng = np.random.default_rng(2)
    T, H, W = 14, 96, 128
    squares = [(12.0, 20.0, 1.2, 0.2, 30), (80.0, 50.0, -0.3, -1.0, 30)]
    frames, alphas, _ = moving_squares(rng, T, H, W, squares)
    fg = alphas.max(0) > 0.5
    params = {**DEFAULT_PARAMS, "grid_stride": 4}
    tr = compute_flow_tracks(frames, fg, params)
    labels = cluster_tracks(tr, (H, W), params)
    assert set(np.unique(labels)) == {1, 2}
    # Which square each track started on.
    q = tr.query_index
    xy = tr.xy[np.arange(tr.num_tracks), q]
    owner = np.array([np.argmax(alphas[:, qi, int(y), int(x)]) for (x, y), qi in zip(xy, q)])
    for k in (0, 1):
        vals, counts = np.unique(labels[owner == k], return_counts=True)
        assert counts.max() / counts.sum() > 0.97
    assert len({int(np.bincount(labels[owner == k]).argmax()) for k in (0, 1)}) == 2
    inst = label_pixels(tr, labels, fg)
    for k in (0, 1):
        ids = inst[(alphas[k] > 0.99) & (alphas[1 - k] < 0.01)]
        assert np.bincount(ids).argmax() == np.bincount(labels[owner == k]).argmax()
        assert (ids == np.bincount(ids).argmax()).mean() > 0.95
    assert np.all(inst[~fg] == 0)


def test_empty_foreground_gives_no_tracks():
    frames = np.random.default_rng(0).integers(0, 255, (5, 32, 40, 3), dtype=np.uint8)
    tr = compute_flow_tracks(frames, np.zeros((5, 32, 40), bool), DEFAULT_PARAMS)
    assert tr.num_tracks == 0 and tr.xy.shape == (0, 5, 2) and tr.stats["count"] == 0


def _carphone(n: int = 30) -> np.ndarray:
    import imageio.v2 as imageio

    path = shared_path("video", "carphone_pristine.mp4")
    reader = imageio.get_reader(str(path))
    try:
        frames = np.stack([f for _, f in zip(range(n), reader)])
    finally:
        reader.close()
    assert frames.shape[0] == n
    return frames


def test_carphone_smoke():
    frames = _carphone()
    t0 = time.perf_counter()
    tr = compute_flow_tracks(frames, None, DEFAULT_PARAMS)
    seconds = time.perf_counter() - t0
    print(f"carphone tracker (whole frame): {tr.stats} in {seconds:.2f} s")
    assert tr.num_tracks > 100
    assert np.all(np.isfinite(tr.xy)) and np.all(np.isfinite(tr.confidence))
    assert tr.visible.any(axis=1).all()
    H, W = frames.shape[1:3]
    vis_xy = tr.xy[tr.visible]
    assert np.all((vis_xy >= 0) & (vis_xy <= [W, H]))
    for key in ("count", "mean_length", "fb_error_median_px", "fb_error_p95_px"):
        assert key in tr.stats and np.isfinite(tr.stats[key])
    assert tr.stats["fb_error_steps"] > 0
    assert tr.stats["fb_error_median_px"] < tr.stats["fb_error_p95_px"] <= 2 * DEFAULT_PARAMS["fb_threshold_px"]
    assert tr.stats["mean_length"] >= DEFAULT_PARAMS["min_track_length"]


def test_carphone_stage(tmp_path):
    """The whole stage on the clip as a monocular scene (placeholder depth 1)."""
    from mogaf.artefact import read_artefact
    from mogaf.priors.stage import run_priors_stage
    from mogaf.scene import SPLIT_CODES, Scene, save_scene
    from mogaf.split import split_scene, write_split

    frames = _carphone()
    T, H, W = frames.shape[:3]
    t = np.concatenate([np.arange(T), np.arange(T)])
    F = 2 * T
    scene = Scene(
        dataset="video",
        name="carphone",
        layout="iphone",
        frame_names=[f"{i:03d}" for i in range(F)],
        images=np.concatenate([frames, frames]),
        K=np.repeat(np.array([[150.0, 0, W / 2], [0, 150.0, H / 2], [0, 0, 1]])[None], F, 0),
        w2c=np.repeat(np.eye(4)[None], F, 0),
        time=t / (T - 1.0),
        time_index=t,
        num_timesteps=T,
        camera_id=np.repeat([0, 1], T),
        source_split=np.repeat([SPLIT_CODES["train"], SPLIT_CODES["val"]], T).astype(np.int8),
        depth=np.ones((F, H, W), np.float32),
    )
    save_scene(tmp_path / "scene.h5", scene, config_digest="test")
    write_split(tmp_path / "split.h5", split_scene(tmp_path / "scene.h5", 0.8))
    t0 = time.perf_counter()
    out = run_priors_stage(tmp_path / "scene.h5", tmp_path / "split.h5", tmp_path / "priors.h5", {})
    seconds = time.perf_counter() - t0
    art = read_artefact(out, "priors")
    a = art.attrs
    print(
        f"carphone stage: { {k: v for k, v in a.items() if k.startswith('track_')} } sources {a['sources']} in {seconds:.2f} s"
    )
    assert art["tracks/xy"].shape[1] == 24 and a["track_count"] == art["tracks/xy"].shape[0] > 20
    assert np.all(np.isfinite(art["tracks/xy"]))
    assert 0 < a["track_fb_error_median_px"] < a["track_fb_error_p95_px"]
    assert a["sources"]["masks"].startswith("motion_segmentation")
    assert len(art["instances/ids"]) >= 1
