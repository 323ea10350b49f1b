"""Forecast renders at the evaluation views, written as PNGs and videos."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from ..artefact.atomic import no_space_error
from ..rendering import render_poses
from ..representation import Model4D


def same_poses_as_before(means: np.ndarray, quats: np.ndarray) -> np.ndarray:
    """(n,) for each forecast step of (G, n, 3) means and (G, n, 4) quats, the
    first of the run of consecutive steps it belongs to whose poses are all
    equal (a frozen forecast: step 0 throughout; a motion that stops: the step
    it stopped at)."""
    n = means.shape[1]
    first = np.arange(n)
    for k in range(1, n):
        if np.array_equal(means[:, k], means[:, k - 1]) and np.array_equal(quats[:, k], quats[:, k - 1]):
            first[k] = first[k - 1]
    return first


def render_forecast_views(model: Model4D, fc: dict[str, Any], frames, params: Mapping[str, Any]) -> list[np.ndarray]:
    """The forecast rendered at every evaluation frame, float64 RGB in [0, 1].
    A frame seen from the same camera as an earlier one, with the same poses
    (a frozen forecast at a fixed view), is that render again: the renderer
    is deterministic, so it is the same image."""
    index = {int(t): i for i, t in enumerate(fc["timesteps"])}
    first = same_poses_as_before(fc["means"], fc["quats"])
    rendered: dict[tuple, np.ndarray] = {}
    renders = []
    for f in range(frames.num_frames):
        i = index[int(frames.time_index[f])]
        key = (int(first[i]), frames.K[f].tobytes(), frames.w2c[f].tobytes())
        if key in rendered:  # a copy: each frame's image is its own array
            renders.append(rendered[key].copy())
            continue
        out = render_poses(
            model, fc["means"][:, i], fc["quats"][:, i], frames.K[f], frames.w2c[f], frames.width, frames.height
        )
        rendered[key] = np.clip(out.features[..., :3].detach().cpu().numpy().astype(np.float64), 0.0, 1.0)
        renders.append(rendered[key])
    return renders


def _save_png(path: Path, img: np.ndarray) -> None:
    import imageio.v3 as iio

    from ..datasets.images import to_uint8  # local: it imports cv2, which only PNG writing needs

    path.parent.mkdir(parents=True, exist_ok=True)
    # zlib level 1: the same pixels, files about 8 % larger, written in less than half the time
    encoded = iio.imwrite("<bytes>", to_uint8(np.asarray(img) * 255.0), extension=".png", compress_level=1)
    with open(path, "wb") as fh:  # a plain write: a full disk is an OSError with its errno
        fh.write(encoded)


def ffmpeg_available() -> bool:
    """Whether imageio can encode mp4 here (imageio-ffmpeg and its binary)."""
    try:
        import imageio_ffmpeg

        return bool(imageio_ffmpeg.get_ffmpeg_exe())
    except (ImportError, RuntimeError, OSError):
        return False


def _encode_mp4(path: Path, frames: list[np.ndarray], fps: int) -> None:
    """H.264 mp4 (crf 16: visually lossless; preset veryfast: a few seconds for
    a demo's videos; yuv420p) through ffmpeg, checking its exit status:
    imageio's writer ignores it, so a full disk left a truncated video."""
    import subprocess

    import imageio_ffmpeg

    h, w = frames[0].shape[:2]
    cmd = [
        imageio_ffmpeg.get_ffmpeg_exe(),
        "-y",
        "-f",
        "rawvideo",
        "-pix_fmt",
        "rgb24",
        "-s",
        f"{w}x{h}",
        "-r",
        str(int(fps)),
        "-i",
        "-",
        "-an",
        "-vcodec",
        "libx264",
        "-pix_fmt",
        "yuv420p",
        "-crf",
        "16",
        "-preset",
        "veryfast",
        "-v",
        "error",
        str(path),
    ]
    data = b"".join(np.ascontiguousarray(f, dtype=np.uint8).tobytes() for f in frames)
    res = subprocess.run(cmd, input=data, capture_output=True, check=False)
    if res.returncode != 0:
        text = res.stderr.decode(errors="replace").strip()
        full = no_space_error(RuntimeError(text))
        if full is not None:
            raise full
        raise RuntimeError(f"ffmpeg exited with status {res.returncode}: {text.splitlines()[-1] if text else ''}")


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
            _encode_mp4(path, frames, fps)
            return
        except RuntimeError:
            path.unlink(missing_ok=True)  # a broken encoder: no half-written mp4 beside the gif
    # Without ffmpeg imageio would pick another plugin for ".mp4" (tifffile, which refuses fps).
    iio2.mimsave(path.with_suffix(".gif"), frames, format="GIF", duration=1.0 / max(fps, 1))


@contextlib.contextmanager
def video_encoder() -> Iterator[Callable[[Path, list[np.ndarray], int], None]]:
    """`_write_video` on a thread of its own, so that ffmpeg encodes one video
    while the caller goes on (the next method's renders and metrics). Leaving
    the block waits for every video and raises the first one's error."""
    pending = []
    with ThreadPoolExecutor(max_workers=1) as pool:
        yield lambda path, panels, fps: pending.append(pool.submit(_write_video, path, panels, fps))
        for video in pending:
            video.result()
