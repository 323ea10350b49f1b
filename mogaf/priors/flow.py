"""Dense optical flow between consecutive frames (OpenCV DIS or RLOF).

Flows are (H, W, 2) float32 arrays in pixels: flow[j, i] = (dx, dy) moves the
pixel centred at array coordinates (i, j) to (i + dx, j + dy) in the other
frame. Positions handled here are array coordinates (pixel centre = integer);
the +0.5 image convention of mogaf.camera is applied only on output.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import cv2
import numpy as np

from ..errors import MogafError
from .params import load_settings

DIS_PRESETS = {
    "ultrafast": cv2.DISOpticalFlow_PRESET_ULTRAFAST,
    "fast": cv2.DISOpticalFlow_PRESET_FAST,
    "medium": cv2.DISOpticalFlow_PRESET_MEDIUM,
}
FLOW_METHODS = ("dis", "rlof")


class FlowEstimator:
    """Callable `(frame_a, frame_b) -> flow a->b` for uint8 RGB frames."""

    def __init__(self, params: Mapping[str, Any]):
        params = load_settings(params)
        self.method = str(params.flow_method).lower()
        if self.method not in FLOW_METHODS:
            raise MogafError(f"priors: flow_method {self.method!r} is not one of {FLOW_METHODS}")
        if self.method == "dis":
            preset = str(params.dis_preset).lower()
            if preset not in DIS_PRESETS:
                raise MogafError(f"priors: dis_preset {preset!r} is not one of {tuple(DIS_PRESETS)}")
            self._dis = cv2.DISOpticalFlow_create(DIS_PRESETS[preset])
            # Finest pyramid level: 0 = full resolution (presets stop at 1 or 2).
            self._dis.setFinestScale(int(params.dis_finest_scale))
            # Variational refinement keeps sub-pixel accuracy on smooth motion.
            self._dis.setUseSpatialPropagation(True)
        elif not hasattr(cv2, "optflow") or not hasattr(cv2.optflow, "calcOpticalFlowDenseRLOF"):
            raise MogafError("priors: flow_method 'rlof' needs opencv-contrib (cv2.optflow); use 'dis'")

    def __call__(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        if self.method == "dis":
            ga = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY)
            gb = cv2.cvtColor(b, cv2.COLOR_RGB2GRAY)
            flow = self._dis.calc(ga, gb, None)
        else:
            flow = cv2.optflow.calcOpticalFlowDenseRLOF(
                np.ascontiguousarray(a[..., ::-1]), np.ascontiguousarray(b[..., ::-1]), None
            )
        flow = np.asarray(flow, dtype=np.float32)
        # Flow solvers can emit NaN in degenerate (constant) images.
        return np.nan_to_num(flow, nan=0.0, posinf=0.0, neginf=0.0)


def consecutive_flows(frames: np.ndarray, params: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Forward flows t->t+1 and backward flows t+1->t, each (T-1, H, W, 2)."""
    T, H, W = frames.shape[:3]
    est = FlowEstimator(params)
    fwd = np.zeros((max(T - 1, 0), H, W, 2), np.float32)
    bwd = np.zeros_like(fwd)
    for t in range(T - 1):
        fwd[t] = est(frames[t], frames[t + 1])
        bwd[t] = est(frames[t + 1], frames[t])
    return fwd, bwd


def sample(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear samples of `image` (H, W, C) at array coordinates xy (N, 2)."""
    n = xy.shape[0]
    if n == 0:
        return np.zeros((0,) + image.shape[2:], np.float32)
    mx = np.ascontiguousarray(xy[:, 0], dtype=np.float32).reshape(1, n)
    my = np.ascontiguousarray(xy[:, 1], dtype=np.float32).reshape(1, n)
    # cv2.remap handles at most 4 channels and rows of at most 32767 columns.
    chunks = []
    for s in range(0, n, 32000):
        chunks.append(
            cv2.remap(
                image, mx[:, s : s + 32000], my[:, s : s + 32000], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
            )
        )
    out = np.concatenate(chunks, axis=1)[0]
    return out.reshape((n,) + image.shape[2:]).astype(np.float32, copy=False)


def sample_patches(image: np.ndarray, xy: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Bilinear patches (N, K, C) of `image` around xy (N, 2) at `offsets` (K, 2)."""
    pts = (xy[:, None, :] + offsets[None]).reshape(-1, 2)
    out = sample(image, pts)
    return out.reshape(xy.shape[0], offsets.shape[0], -1)
