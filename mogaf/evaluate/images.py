"""Forecast renders at the evaluation views, written as PNGs and videos."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..rendering import render_poses
from ..representation import Model4D


def render_forecast_views(model: Model4D, fc: dict[str, Any], frames, params: Mapping[str, Any]) -> list[np.ndarray]:
    index = {int(t): i for i, t in enumerate(fc["timesteps"])}
    renders = []
    for f in range(frames.num_frames):
        i = index[int(frames.time_index[f])]
        out = render_poses(
            model, fc["means"][:, i], fc["quats"][:, i], frames.K[f], frames.w2c[f], frames.width, frames.height
        )
        renders.append(np.clip(out.features[..., :3].detach().cpu().numpy().astype(np.float64), 0.0, 1.0))
    return renders


def _save_png(path: Path, img: np.ndarray) -> None:
    import imageio.v3 as iio

    from ..datasets.images import to_uint8  # local: it imports cv2, which only PNG writing needs

    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, to_uint8(np.asarray(img) * 255.0))


def ffmpeg_available() -> bool:
    """Whether imageio can encode mp4 here (imageio-ffmpeg and its binary)."""
    try:
        import imageio_ffmpeg

        return bool(imageio_ffmpeg.get_ffmpeg_exe())
    except (ImportError, RuntimeError, OSError):
        return False


def _write_video(path: Path, panels: list[np.ndarray], fps: int) -> None:
    """uint8 frames (mogaf.video.labelled_row) as mp4 (gif beside it when ffmpeg is unavailable)."""
    import imageio.v2 as iio2

    frames = []
    for img in panels:
        h, w = img.shape[:2]
        img = np.pad(img, ((0, h % 2), (0, w % 2), (0, 0)))  # even sizes for yuv420p
        frames.append(img)
    if ffmpeg_available():
        try:
            with iio2.get_writer(
                path, format="FFMPEG", fps=fps, codec="libx264", quality=8, macro_block_size=2, ffmpeg_log_level="error"
            ) as writer:
                for f in frames:
                    writer.append_data(f)
            return
        except (RuntimeError, OSError):
            path.unlink(missing_ok=True)  # a broken encoder: no half-written mp4 beside the gif
    # Without ffmpeg imageio would pick another plugin for ".mp4" (tifffile, which refuses fps).
    iio2.mimsave(path.with_suffix(".gif"), frames, format="GIF", duration=1.0 / max(fps, 1))
