"""Labelled video frames: panels side by side, each named in a strip above
it, and a caption (method, time step, view) on top, so a person opening a
video knows what every panel is."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

BACKGROUND = 255  # white strips, black text


def _text_scale(width: int) -> float:
    """OpenCV font scale that fits a short label in a panel `width` pixels wide."""
    return float(np.clip(width / 420.0, 0.3, 1.0))


def text_strip(width: int, text: str, scale: float) -> np.ndarray:
    """(h, width, 3) uint8 white strip with `text` in black, clipped to the width."""
    import cv2

    font = cv2.FONT_HERSHEY_SIMPLEX
    (_, th), base = cv2.getTextSize("Ag", font, scale, 1)
    h = th + base + 6
    strip = np.full((h, width, 3), BACKGROUND, np.uint8)
    cv2.putText(strip, text, (3, 3 + th), font, scale, (0, 0, 0), 1, cv2.LINE_AA)
    return strip


def to_uint8(img: np.ndarray) -> np.ndarray:
    """[0, 1] float image (H, W, 3) -> uint8."""
    from .datasets.images import (
        to_uint8 as scaled_to_uint8,  # local: mogaf.datasets.images imports cv2, which only this path needs
    )

    return scaled_to_uint8(np.asarray(img, np.float64) * 255.0)


def labelled_row(images: Sequence[np.ndarray], labels: Sequence[str], caption: str) -> np.ndarray:
    """uint8 frame: the images (uint8 or [0, 1] floats, one height) side by side,
    each under its label, the caption across the top."""
    if len(images) != len(labels) or not images:
        raise ValueError("labelled_row: one label per image, at least one image")
    tiles = [img if img.dtype == np.uint8 else to_uint8(img) for img in images]
    scale = _text_scale(tiles[0].shape[1])
    columns = [
        np.concatenate([text_strip(t.shape[1], label, scale), t[..., :3]], axis=0) for t, label in zip(tiles, labels)
    ]
    body = np.concatenate(columns, axis=1)
    return np.concatenate([text_strip(body.shape[1], caption, scale), body], axis=0)
