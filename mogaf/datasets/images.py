"""Safe image reading and exact integer downscaling for the dataset readers.

- `png_size` reads only a PNG's header, so a file announcing a huge size is
  refused before any pixel buffer is allocated.
- `read_image` decodes with OpenCV (fast) and returns RGB(A) channel order,
  8-bit (16-bit files are rounded down to 8 bit), or raises one line naming
  the file when it is missing, corrupt, truncated or not an image.
- `downscale_*` shrink by an integer factor s over s x s blocks: the area mean
  for colours and alpha (cv2.INTER_AREA is the exact block mean for integer
  factors) and the block majority for id masks (ties go to the smallest id),
  so no id that is absent from a block is ever invented. Images whose side is
  not a multiple of s lose their last (side mod s) rows/columns; with pixel
  centres at +0.5 intrinsics then scale exactly: K' = diag(1/s, 1/s, 1) K.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

import cv2
import numpy as np

from ..errors import input_error
from .common import MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def png_size(path: str | os.PathLike) -> tuple[int, int, int] | None:
    """(width, height, channels) from a PNG header; None if not a PNG.

    Raises one line for a missing/unreadable file, a truncated header or an
    implausible size.
    """
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            head = fh.read(33)
    except FileNotFoundError:
        raise input_error(p, "missing image") from None
    except IsADirectoryError:
        raise input_error(p, "is a folder, expected an image") from None
    except OSError as exc:
        raise input_error(p, f"cannot be read ({exc.strerror or exc.__class__.__name__})") from None
    if not head.startswith(PNG_MAGIC):
        return None
    if len(head) < 33 or head[12:16] != b"IHDR":
        raise input_error(p, "corrupt PNG (truncated or missing IHDR header)")
    width, height, _bit_depth, colour_type = struct.unpack(">IIBB", head[16:26])
    channels = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}.get(colour_type)
    if channels is None:
        raise input_error(p, f"corrupt PNG (unknown colour type {colour_type})")
    if (
        width == 0
        or height == 0
        or width > MAX_IMAGE_SIDE
        or height > MAX_IMAGE_SIDE
        or width * height > MAX_IMAGE_PIXELS
    ):
        raise input_error(p, f"PNG header announces an implausible size {width}x{height}")
    return width, height, channels


def read_image(
    path: str | os.PathLike, *, expect_size: tuple[int, int] | None = None, what: str = "image"
) -> np.ndarray:
    """Decode an image to (H, W) or (H, W, 3|4) uint8 in RGB(A) order.

    `expect_size` is (width, height); a mismatch (checked from the header
    before decoding when the file is a PNG) is a one-line error.
    """
    p = Path(path)
    header = png_size(p)
    if header is not None and expect_size is not None and (header[0], header[1]) != tuple(expect_size):
        raise input_error(p, f"{what} is {header[0]}x{header[1]}, expected {expect_size[0]}x{expect_size[1]}")
    if header is None and p.stat().st_size == 0:
        raise input_error(p, f"empty file, expected a PNG {what}")
    img = cv2.imread(os.fspath(p), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise input_error(p, f"unreadable or corrupt {what} (OpenCV cannot decode it)")
    if header is not None and img.shape[:2] != (header[1], header[0]):
        raise input_error(p, f"corrupt PNG: decoded size {img.shape[1]}x{img.shape[0]} differs from the header")
    if img.dtype == np.uint16:
        img = ((img.astype(np.uint32) + 128) // 257).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise input_error(p, f"{what} has unsupported pixel type {img.dtype}")
    if img.ndim == 3:
        if img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        elif img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
        elif img.shape[2] == 1:
            img = img[..., 0]
        else:
            raise input_error(p, f"{what} has {img.shape[2]} channels")
    if expect_size is not None and (img.shape[1], img.shape[0]) != tuple(expect_size):
        raise input_error(p, f"{what} is {img.shape[1]}x{img.shape[0]}, expected {expect_size[0]}x{expect_size[1]}")
    return img


def read_label_image(
    path: str | os.PathLike, *, expect_size: tuple[int, int] | None = None, what: str = "mask"
) -> np.ndarray:
    """Decode an id mask (8 or 16 bit, single channel or equal channels); dtype kept."""
    p = Path(path)
    header = png_size(p)
    if header is not None and expect_size is not None and (header[0], header[1]) != tuple(expect_size):
        raise input_error(p, f"{what} is {header[0]}x{header[1]}, expected {expect_size[0]}x{expect_size[1]}")
    if header is None and p.stat().st_size == 0:
        raise input_error(p, f"empty file, expected a PNG {what}")
    img = cv2.imread(os.fspath(p), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise input_error(p, f"unreadable or corrupt {what} (OpenCV cannot decode it)")
    if img.dtype not in (np.uint8, np.uint16):
        raise input_error(p, f"{what} has unsupported pixel type {img.dtype}")
    if img.ndim == 3:
        chans = img[..., :3] if img.shape[2] >= 3 else img
        if not all(np.array_equal(chans[..., 0], chans[..., c]) for c in range(1, chans.shape[2])):
            raise input_error(p, f"{what} must be single-channel (ids), got differing colour channels")
        img = chans[..., 0]
    if expect_size is not None and (img.shape[1], img.shape[0]) != tuple(expect_size):
        raise input_error(p, f"{what} is {img.shape[1]}x{img.shape[0]}, expected {expect_size[0]}x{expect_size[1]}")
    return img


def _crop(img: np.ndarray, s: int) -> np.ndarray:
    H, W = img.shape[:2]
    return img[: H - H % s, : W - W % s]


def downscale_area(img: np.ndarray, s: int) -> np.ndarray:
    """Block mean over s x s blocks (uint8 in, uint8 out; float in, float out)."""
    if s == 1:
        return img
    img = _crop(img, s)
    H, W = img.shape[:2]
    return cv2.resize(img, (W // s, H // s), interpolation=cv2.INTER_AREA)


def downscale_labels(mask: np.ndarray, s: int, ids: np.ndarray | None = None) -> np.ndarray:
    """Block majority of an id mask; ties go to the smallest id.

    `ids` must list every id present in `mask` (e.g. from np.bincount).
    """
    if s == 1:
        return mask
    mask = _crop(mask, s)
    H, W = mask.shape
    if ids is None:
        ids = np.unique(mask)
    ids = np.sort(np.asarray(ids))
    if ids.size == 1:
        return np.full((H // s, W // s), ids[0], dtype=mask.dtype)
    if ids.size > 64:
        # Many ids: take the centre-most pixel of each block (never invents ids).
        return mask[s // 2 :: s, s // 2 :: s].copy()
    # INTER_AREA of a 0/1 indicator is count / s^2 per block, computed the
    # same way for every id, so equal counts compare equal and argmax keeps
    # the first (smallest) id on ties.
    shares = np.stack(
        [cv2.resize((mask == i).astype(np.float32), (W // s, H // s), interpolation=cv2.INTER_AREA) for i in ids]
    )
    return ids[np.argmax(shares, axis=0)].astype(mask.dtype)


def composite_downscale(rgba: np.ndarray, background: np.ndarray, s: int) -> tuple[np.ndarray, np.ndarray]:
    """Composite RGBA uint8 over `background` (RGB in [0, 1]) and shrink by s.

    Exact in real arithmetic: the block mean of rgb*a + bg*(1-a) equals
    mean(rgb*a) + bg*(1 - mean(a)); premultiplied colours are averaged in
    16 bit. Returns (rgb uint8 (h, w, 3), alpha uint8 (h, w)).
    """
    work = rgba.astype(np.uint16)
    a = work[..., 3:4].copy()
    work[..., 3] = 255
    np.multiply(work, a, out=work)  # (rgb*a, 255*a), at most 65025
    small = downscale_area(work, s).astype(np.float32) * (1.0 / 255.0)
    a_small = small[..., 3] * (1.0 / 255.0)
    bg = (np.asarray(background, dtype=np.float32) * 255.0).reshape(1, 1, 3)
    rgb = small[..., :3] + bg * (1.0 - a_small[..., None])
    return to_uint8(rgb), to_uint8(a_small * 255.0)


def to_uint8(img: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
