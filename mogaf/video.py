"""Labelled video frames: panels side by side, each named in a strip above
it (and, where given, a strip below it, such as the error panel's colour
scale), and a caption (method, time step, view) on top, so a person opening
a video knows what every panel is. Small scenes are enlarged by an integer
factor, nearest neighbour: every rendered pixel stays one block."""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np

BACKGROUND = 255  # white strips, black text


def text_scale(width: int) -> float:
    """OpenCV font scale that fits a short label in a panel `width` pixels wide."""
    return float(np.clip(width / 420.0, 0.3, 1.0))


@functools.lru_cache(maxsize=256)
def text_strip(width: int, text: str, scale: float) -> np.ndarray:
    """(h, width, 3) uint8 white strip with `text` in black, clipped to the width
    (cached, read-only: a video draws the same labels on every frame)."""
    import cv2

    font = cv2.FONT_HERSHEY_SIMPLEX
    (_, th), base = cv2.getTextSize("Ag", font, scale, 1)
    h = th + base + 6
    strip = np.full((h, width, 3), BACKGROUND, np.uint8)
    cv2.putText(strip, text, (3, 3 + th), font, scale, (0, 0, 0), 1, cv2.LINE_AA)
    strip.flags.writeable = False
    return strip


def to_uint8(img: np.ndarray) -> np.ndarray:
    """[0, 1] float image (H, W, 3) -> uint8."""
    from .datasets.images import (
        to_uint8 as scaled_to_uint8,  # local: mogaf.datasets.images imports cv2, which only this path needs
    )

    return scaled_to_uint8(np.asarray(img, np.float64) * 255.0)


def enlargement(width: int, min_width: int) -> int:
    """The integer factor that makes a panel `width` pixels wide at least
    `min_width` wide (1 when it already is, or when min_width is 0)."""
    if min_width <= 0 or width >= min_width:
        return 1
    return -(-min_width // max(width, 1))


def enlarge(img: np.ndarray, factor: int) -> np.ndarray:
    """Each pixel as a factor x factor block (no interpolation)."""
    if factor == 1:
        return img
    if img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3:
        import cv2  # the same blocks as np.repeat, several times faster

        h, w = img.shape[:2]
        return cv2.resize(img, (w * factor, h * factor), interpolation=cv2.INTER_NEAREST)
    return np.repeat(np.repeat(img, factor, axis=0), factor, axis=1)


def error_panel(pred: np.ndarray, gt: np.ndarray, vmax: float) -> np.ndarray:
    """uint8 (H, W, 3): the mean absolute RGB error per pixel, 0..vmax (clipped)
    mapped through the inferno colour map (colour_legend draws its scale)."""
    import cv2

    err = np.abs(np.asarray(pred, np.float64) - np.asarray(gt, np.float64)).mean(axis=-1)
    levels = np.clip(np.rint(255.0 * err / vmax), 0, 255).astype(np.uint8)
    return cv2.applyColorMap(levels, cv2.COLORMAP_INFERNO)[..., ::-1].copy()


def colour_legend(width: int, vmax: float, scale: float) -> np.ndarray:
    """(h, width, 3) uint8: the error panel's colour bar from 0 to vmax, labelled."""
    import cv2

    ramp = np.tile(np.linspace(0, 255, max(width - 6, 1)).round().astype(np.uint8)[None], (8, 1))
    bar = cv2.applyColorMap(ramp, cv2.COLORMAP_INFERNO)[..., ::-1]
    strip = np.full((8 + 4, width, 3), BACKGROUND, np.uint8)
    strip[2:10, 3 : 3 + bar.shape[1]] = bar
    low = text_strip(width, "0", scale)
    high = text_strip(width, f">= {vmax:g} mean |error|", scale)
    labels = np.full_like(low, BACKGROUND)
    labels[:, : width // 4] = low[:, : width // 4]
    text = high[:, : max(width - width // 4, 1)]
    labels[:, width - text.shape[1] :] = text
    return np.concatenate([strip, labels], axis=0)


def labelled_row(
    images: Sequence[np.ndarray],
    labels: Sequence[str],
    caption: str,
    footers: Sequence[np.ndarray | None] | None = None,
) -> np.ndarray:
    """uint8 frame: the images (uint8 or [0, 1] floats, one height) side by side,
    each under its label and above its footer strip (if any), the caption
    across the top."""
    if len(images) != len(labels) or not images:
        raise ValueError("labelled_row: one label per image, at least one image")
    footers = list(footers) if footers is not None else [None] * len(images)
    if len(footers) != len(images):
        raise ValueError("labelled_row: one footer (or None) per image")
    tiles = [img if img.dtype == np.uint8 else to_uint8(img) for img in images]
    scale = text_scale(tiles[0].shape[1])
    foot_h = max((f.shape[0] for f in footers if f is not None), default=0)
    columns = []
    for t, label, foot in zip(tiles, labels, footers):
        parts = [text_strip(t.shape[1], label, scale), t[..., :3]]
        if foot_h:
            pad = np.full((foot_h, t.shape[1], 3), BACKGROUND, np.uint8)
            if foot is not None:
                pad[: foot.shape[0], : foot.shape[1]] = foot[:, : t.shape[1]]
            parts.append(pad)
        columns.append(np.concatenate(parts, axis=0))
    body = np.concatenate(columns, axis=1)
    return np.concatenate([text_strip(body.shape[1], caption, scale), body], axis=0)
