"""Labelled video frames (mogaf.video): every panel named, the caption on top."""

from __future__ import annotations

import numpy as np
import pytest

from mogaf.video import labelled_row, text_strip


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
