"""The split stage: scene.h5 frame metadata -> the Split (split_scene; written by write_split)."""

from __future__ import annotations

import os

import numpy as np

from ..artefact import open_artefact, read_rows
from ..scene import SCENE_STAGE, check_scene_file
from .core import Split
from .protocol import make_split


def split_scene(scene_h5: str | os.PathLike, ratio: float) -> Split:
    """Read per-frame metadata of scene.h5 (no images) and build the split."""
    with open_artefact(scene_h5, SCENE_STAGE) as fh:
        n, T = check_scene_file(fh, scene_h5)
        rows = np.arange(n)
        meta = {k: read_rows(fh, f"frames/{k}", rows) for k in ("time", "time_index", "source_split", "camera_id")}
        layout = fh.attrs["layout"]
        layout = layout.decode() if isinstance(layout, bytes) else str(layout)
    return make_split(
        meta["time"], meta["time_index"], T, meta["source_split"], meta["camera_id"], layout, ratio, scene_h5
    )
