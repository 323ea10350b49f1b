"""Contact sheet of a generated synthetic scene (for eyeballing, not for the pipeline)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np

from ..artefact import write_bytes
from ..errors import MogafError
from .generate import frame_name

PALETTE = np.array(
    [
        [40, 40, 40],
        [230, 80, 60],
        [60, 160, 230],
        [250, 200, 40],
        [120, 220, 120],
        [200, 100, 220],
        [240, 150, 200],
        [100, 230, 220],
        [180, 180, 90],
        [255, 255, 255],
    ],
    dtype=np.uint8,
)


def _read_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise FileNotFoundError(path)
    return img[..., ::-1] if img.ndim == 3 else img


def contact_sheet(
    scene_dir: str | os.PathLike, out_png: str | os.PathLike, times: list[int] | None = None, zoom: int = 2
) -> Path:
    """Rows = times; columns = train RGB, test 1 RGB, test 2 RGB, train instance ids
    (with visible GT tracks as dots), train depth, test 1 covisible mask."""
    root = Path(scene_dir)
    T = len(json.loads((root / "splits" / "train.json").read_text())["frame_names"])
    if times is None:
        times = [0, int(0.6 * (T - 1)), T - 1]
    tracks = np.load(root / "mogaf_gt" / "tracks2d.npy")
    visible = np.load(root / "mogaf_gt" / "visible.npy")
    num_cameras = 1 + len({int(c) for c in json.loads((root / "splits" / "val.json").read_text())["camera_ids"]})
    rows = []
    for ti in times:
        cols = [_read_rgb(root / "rgb" / "1x" / f"{frame_name(c, ti)}.png") for c in range(num_cameras)]
        inst = _read_rgb(root / "mogaf_gt" / "instance" / "1x" / f"{frame_name(0, ti)}.png")
        ic = PALETTE[np.minimum(inst, len(PALETTE) - 1)].copy()
        for u, v in tracks[visible[:, ti], ti]:
            ic[int(v), int(u)] = 255
        cols.append(ic)
        depth = np.load(root / "depth" / "1x" / f"{frame_name(0, ti)}.npy")[..., 0]
        d8 = np.clip(255 * (depth - depth.min()) / max(float(np.ptp(depth)), 1e-9), 0, 255).astype(np.uint8)
        cols.append(cv2.applyColorMap(d8, cv2.COLORMAP_VIRIDIS)[..., ::-1])
        cov = _read_rgb(root / "covisible" / "1x" / "val" / f"{frame_name(1, ti)}.png")
        cols.append(np.repeat(cov[..., None], 3, axis=2))
        sep = np.full((cols[0].shape[0], 2, 3), 255, np.uint8)
        row = cols[0]
        for c in cols[1:]:
            row = np.concatenate([row, sep, c], axis=1)
        rows.append(row)
        rows.append(np.full((2, row.shape[1], 3), 255, np.uint8))
    sheet = np.concatenate(rows[:-1], axis=0)
    sheet = cv2.resize(sheet, None, fx=zoom, fy=zoom, interpolation=cv2.INTER_NEAREST)
    ok, encoded = cv2.imencode(".png", np.ascontiguousarray(sheet[..., ::-1]))
    if not ok:
        raise MogafError(f"{out_png}: OpenCV could not encode the contact sheet")
    return write_bytes(out_png, encoded.tobytes())
