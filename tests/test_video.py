"""Labelled video frames (mogaf.video): every panel named, the caption on top."""

from __future__ import annotations

import numpy as np
import pytest

from mogaf.video import colour_legend, enlarge, enlargement, error_panel, labelled_row, text_strip


def test_labelled_row_puts_each_label_above_its_panel_and_the_caption_on_top():
    panels = [np.zeros((60, 80, 3)), np.ones((60, 80, 3)), np.full((60, 80, 3), 0.5)]
    frame = labelled_row(panels, ["GT", "MoGaF (Ours)", "|error|"], "MoGaF (Ours), time step 7, view 1_00007")
    strip = text_strip(80, "x", 0.3).shape[0]
    assert frame.dtype == np.uint8 and frame.shape == (60 + 2 * strip, 240, 3)
    body = frame[2 * strip :]
    np.testing.assert_array_equal(body[:, :80], 0)
    np.testing.assert_array_equal(body[:, 80:160], 255)
    # text is drawn: every label strip and the caption strip hold dark pixels on white
    for x0 in (0, 80, 160):
        label = frame[strip : 2 * strip, x0 : x0 + 80]
        assert (label < 128).any() and (label == 255).mean() > 0.5
    assert (frame[:strip] < 128).any()
    # an empty label leaves its strip blank
    blank = labelled_row([np.zeros((10, 80, 3))], [""], "")
    assert (blank[: 2 * strip] == 255).all()


def test_labelled_row_refuses_a_missing_label():
    with pytest.raises(ValueError):
        labelled_row([np.zeros((4, 4, 3))], [], "caption")


def test_without_ffmpeg_the_video_is_a_gif_beside_the_mp4_name(tmp_path, monkeypatch):
    """Without imageio-ffmpeg, imageio would hand '.mp4' to another plugin (tifffile
    refuses fps): the evaluate stage writes a gif instead, and no mp4."""
    import imageio.v3 as iio

    from mogaf.evaluate import images

    frames = [np.full((21, 33, 3), 20 * i, np.uint8) for i in range(4)]
    monkeypatch.setattr(images, "ffmpeg_available", lambda: False)
    images._write_video(tmp_path / "mogaf.mp4", frames, 5)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mogaf.gif"]
    assert iio.imread(tmp_path / "mogaf.gif", index=None).shape == (4, 22, 34, 3)


def test_small_panels_are_enlarged_by_an_integer_factor_pixel_for_pixel():
    assert enlargement(160, 320) == 2 and enlargement(100, 320) == 4 and enlargement(400, 320) == 1
    assert enlargement(64, 0) == 1
    for img in (np.arange(6, dtype=np.uint8).reshape(2, 3, 1), np.arange(30, dtype=np.uint8).reshape(2, 5, 3)):
        big = enlarge(img, 3)
        assert big.shape == (6, 3 * img.shape[1], img.shape[2])
        np.testing.assert_array_equal(big, np.repeat(np.repeat(img, 3, axis=0), 3, axis=1))


def test_error_panel_maps_mean_error_through_a_fixed_scale_with_its_legend_below():
    gt = np.zeros((4, 5, 3))
    pred = np.zeros((4, 5, 3))
    pred[0, 0] = 0.5  # mean |error| 0.5: the top of the scale
    pred[1, 1] = 1.0  # beyond it: clipped to the top
    panel = error_panel(pred, gt, vmax=0.5)
    assert panel.dtype == np.uint8 and panel.shape == (4, 5, 3)
    np.testing.assert_array_equal(panel[0, 0], panel[1, 1])
    assert panel[0, 0].sum() > panel[2, 2].sum()  # the top of inferno is bright, zero error dark
    legend = colour_legend(120, 0.5, 0.3)
    frame = labelled_row([gt, gt, panel], ["GT", "m", "|error|"], "c", footers=[None, None, legend])
    strip = text_strip(5, "x", 0.3).shape[0]
    assert frame.shape[0] == 2 * strip + 4 + legend.shape[0]
    # the footer sits under the error panel only; under the others the strip stays blank
    below = frame[2 * strip + 4 :]
    assert (below[:, :10] == 255).all() and (below[:, 10:] != 255).any()
    with pytest.raises(ValueError, match="one footer"):
        labelled_row([gt], ["GT"], "c", footers=[None, None])
