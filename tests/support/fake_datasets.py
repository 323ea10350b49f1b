"""Tiny datasets on disk for the tests (no shared data needed).

`fake_dnerf` and `fake_iphone` write a few small frames in the D-NeRF and the
DyCheck iPhone (+ Shape-of-Motion) layouts. Cameras circle the origin and
look at it. Each image draws the point `MARKER` (a 3D point) as one bright
pixel, computed here with the dataset's own camera convention (OpenGL c2w
for D-NeRF, orientation/position for DyCheck) independently of mogaf.camera,
so readers can be checked against it.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np

MARKER = np.array([0.3, -0.25, 0.2])


def write_png(path: str | Path, image: np.ndarray) -> Path:
    """Write uint8/uint16 gray, RGB or RGBA (RGB order) as PNG."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    elif img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_RGBA2BGRA)
    if not cv2.imwrite(str(p), img):
        raise OSError(f"cannot write {p}")
    return p


def write_json(path: str | Path, obj) -> Path:
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(obj, indent=1))
    return p


def _look_at_c2w_gl(eye: np.ndarray, target=None, up=None) -> np.ndarray:
    """OpenGL camera-to-world (x right, y up, z backward) looking at target (default: the origin; up: +z)."""
    target = np.zeros(3) if target is None else target
    up = np.array([0.0, 0.0, 1.0]) if up is None else up
    back = eye - target
    back = back / np.linalg.norm(back)
    right = np.cross(up, back)
    right = right / np.linalg.norm(right)
    true_up = np.cross(back, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, back, eye
    return c2w


def _marker_pixel_gl(c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> tuple[int, int]:
    """Pixel (col, row) holding MARKER, with OpenGL maths (centres at +0.5)."""
    p = np.linalg.inv(c2w) @ np.append(MARKER, 1.0)
    depth = -p[2]
    u = cx + fx * p[0] / depth
    v = cy - fy * p[1] / depth
    return int(np.floor(u)), int(np.floor(v))


def fake_dnerf(
    root: str | Path,
    *,
    counts: Mapping[str, int] | None = None,
    size: int = 16,
    rgba: bool = True,
    masks: bool = True,
    ply: str | None = "binary",
    class_names: Mapping[int, str] | None = None,
) -> Path:
    """A D-NeRF scene with frames on a uniform time grid shared by all splits.

    Masks: id 1 ("ball") on the left half of each image's top rows, id 2
    ("cloth") on the marker pixel. Alpha is 255 on the masks and on the
    marker, 0 elsewhere (RGB under alpha 0 is random).
    """
    root = Path(root)
    counts = dict(counts or {"train": 4, "val": 2, "test": 2})
    names = dict(class_names or {0: "background", 1: "ball", 2: "cloth"})
    total = sum(counts.values())
    times = np.linspace(0.0, 1.0, total)
    order = np.random.default_rng(0).permutation(total)
    rng = np.random.default_rng(1)
    fov = 0.9
    f = 0.5 * size / np.tan(0.5 * fov)
    k = 0
    for split, n in counts.items():
        frames = []
        for i in range(n):
            ang = 2 * np.pi * k / max(total, 1)
            eye = np.array([2.0 * np.cos(ang), 2.0 * np.sin(ang), 0.7 + 0.1 * (k % 3)])
            c2w = _look_at_c2w_gl(eye)
            col, row = _marker_pixel_gl(c2w, f, f, size / 2, size / 2)
            rgb = rng.integers(0, 256, (size, size, 3), dtype=np.uint8)
            a = np.zeros((size, size), np.uint8)
            ids = np.zeros((size, size), np.uint8)
            ids[: size // 4, : size // 2] = 1
            a[ids > 0] = 255
            if 0 <= col < size and 0 <= row < size:
                ids[row, col] = 2
                a[row, col] = 255
                rgb[row, col] = 255
            stem = f"r_{i:03d}"
            write_png(root / split / f"{stem}.png", np.dstack([rgb, a]) if rgba else rgb)
            if masks:
                write_png(root / split / "masks" / f"{stem}.png", ids)
            frames.append(
                {
                    "file_path": f"./{split}/{stem}",
                    "time": float(times[order[k]]),
                    "transform_matrix": c2w.tolist(),
                    "marker_pixel": [col, row],
                }
            )
            k += 1
        write_json(root / f"transforms_{split}.json", {"camera_angle_x": fov, "frames": frames})
    if masks:
        write_json(root / "class_mapping.json", {str(k): v for k, v in names.items()})
    if ply is not None:
        write_ply(root / "fused.ply", rng.normal(size=(20, 3)), rng.integers(0, 256, (20, 3)), binary=(ply == "binary"))
    return root


def write_ply(path: str | Path, xyz: np.ndarray, rgb: np.ndarray | None = None, *, binary: bool = True) -> Path:
    p = Path(path)
    n = len(xyz)
    props = ["property float x", "property float y", "property float z"]
    if rgb is not None:
        props += ["property uchar red", "property uchar green", "property uchar blue"]
    fmt = "binary_little_endian" if binary else "ascii"
    header = "\n".join(["ply", f"format {fmt} 1.0", "comment fake", f"element vertex {n}", *props, "end_header"]) + "\n"
    if binary:
        fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")] + (
            [("red", "u1"), ("green", "u1"), ("blue", "u1")] if rgb is not None else []
        )
        rec = np.zeros(n, dtype=fields)
        rec["x"], rec["y"], rec["z"] = np.asarray(xyz, np.float32).T
        if rgb is not None:
            rec["red"], rec["green"], rec["blue"] = np.asarray(rgb, np.uint8).T
        p.write_bytes(header.encode() + rec.tobytes())
    else:
        lines = []
        for i in range(n):
            vals = [f"{v:.6f}" for v in xyz[i]] + ([str(int(c)) for c in rgb[i]] if rgb is not None else [])
            lines.append(" ".join(vals))
        p.write_text(header + "\n".join(lines) + "\n")
    return p


def fake_iphone(
    root: str | Path,
    *,
    num_times: int = 5,
    val_cameras: int = 2,
    full_size: tuple[int, int] = (32, 24),
    scale: int = 2,
    depth: bool = True,
    covisible: bool = True,
    keypoints: bool = True,
    som: bool = True,
    colmap_scale: float | None = 2.0,
    track_points: int = 3,
    rgba: bool = True,
) -> Path:
    """A DyCheck iPhone scene: camera 0 moves (train), cameras 1.. are static (val).

    Names are "<camera>_<time:05d>". Train has every time step, each val
    camera every time step except the last. Images are at `full_size / scale`.
    """
    root = Path(root)
    W, H = full_size
    w, h = int(round(W / scale)), int(round(H / scale))
    rng = np.random.default_rng(2)
    f = 0.9 * W
    splits = {
        "train": {"frame_names": [], "camera_ids": [], "time_ids": []},
        "val": {"frame_names": [], "camera_ids": [], "time_ids": []},
    }
    metadata = {}
    markers: dict[str, list[int]] = {}
    for cam in range(1 + val_cameras):
        for t in range(num_times if cam == 0 else num_times - 1):
            name = f"{cam}_{t:05d}"
            ang = 1.1 * cam + (0.3 * t if cam == 0 else 0.0)
            eye = np.array([1.5 * np.cos(ang), 1.5 * np.sin(ang), 0.4])
            c2w_gl = _look_at_c2w_gl(eye)
            # DyCheck: orientation = w2c rotation (OpenCV axes), position = centre.
            R_c2w_cv = c2w_gl[:3, :3] @ np.diag([1.0, -1.0, -1.0])
            cam_json = {
                "focal_length": f,
                "image_size": [W, H],
                "orientation": R_c2w_cv.T.tolist(),
                "pixel_aspect_ratio": 1.0,
                "position": eye.tolist(),
                "principal_point": [W / 2 + 0.25, H / 2 - 0.5],
                "radial_distortion": [0.0, 0.0, 0.0],
                "skew": 0.0,
                "tangential_distortion": [0.0, 0.0],
            }
            write_json(root / "camera" / f"{name}.json", cam_json)
            split = "train" if cam == 0 else "val"
            splits[split]["frame_names"].append(name)
            splits[split]["camera_ids"].append(cam)
            splits[split]["time_ids"].append(t)
            metadata[name] = {"appearance_id": t, "camera_id": cam, "warp_id": t}
            rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
            # Marker with DyCheck's maths: x = R (X - c), pixel = f x/z + pp, then / scale.
            xc = R_c2w_cv.T @ (MARKER - eye)
            u = (f * xc[0] / xc[2] + cam_json["principal_point"][0]) / scale
            v = (f * xc[1] / xc[2] + cam_json["principal_point"][1]) / scale
            col, row = int(np.floor(u)), int(np.floor(v))
            if 0 <= col < w and 0 <= row < h:
                rgb[row, col] = 255
            markers[name] = [col, row]
            write_png(
                root / "rgb" / f"{scale}x" / f"{name}.png",
                np.dstack([rgb, np.full((h, w), 255, np.uint8)]) if rgba else rgb,
            )
            if depth and split == "train":
                root.joinpath("depth", f"{scale}x").mkdir(parents=True, exist_ok=True)
                np.save(
                    root / "depth" / f"{scale}x" / f"{name}.npy", rng.uniform(0.5, 2.0, (h, w, 1)).astype(np.float32)
                )
            if covisible and split == "val":
                write_png(
                    root / "covisible" / f"{scale}x" / "val" / f"{name}.png",
                    (rng.random((h, w)) > 0.5).astype(np.uint8) * 255,
                )
            if keypoints and split == "train":
                kp = [[1.0, 2.0, 1.0], [3.0, 1.0, 1.0], [0.0, 0.0, 0.0]]
                write_json(root / "keypoint" / f"{scale}x" / "train" / f"{name}.json", kp)
            if som:
                fg = np.zeros((h, w), np.uint8)
                fg[h // 4 : h // 2, w // 4 : w // 2] = 255
                write_png(root / "flow3d_preprocessed" / "track_anything" / f"{scale}x" / f"{name}.png", fg)
                if split == "train":
                    d = root / "flow3d_preprocessed" / "aligned_depth_anything_colmap" / f"{scale}x"
                    d.mkdir(parents=True, exist_ok=True)
                    np.save(d / f"{name}.npy", rng.uniform(0.2, 1.0, (h, w)).astype(np.float32))
    names = [n for s in splits.values() for n in s["frame_names"]]
    if som and colmap_scale is not None:
        root.joinpath("flow3d_preprocessed", "colmap").mkdir(parents=True, exist_ok=True)
        np.save(root / "flow3d_preprocessed" / "colmap" / "scale.npy", np.array(colmap_scale))
    if som and track_points:
        d = root / "flow3d_preprocessed" / "2d_tracks" / f"{scale}x"
        d.mkdir(parents=True, exist_ok=True)
        train = splits["train"]["frame_names"]
        for qi, q in enumerate(train):
            for ti, t in enumerate(train):
                arr = np.zeros((track_points, 4), np.float32)
                arr[:, 0] = np.arange(track_points) + qi
                arr[:, 1] = ti
                arr[:, 2] = -3.0
                arr[:, 3] = -2.0
                np.save(d / f"{q}_{t}.npy", arr)
    for split, data in splits.items():
        write_json(root / "splits" / f"{split}.json", data)
    write_json(
        root / "dataset.json",
        {
            "count": len(names),
            "ids": names,
            "num_exemplars": num_times,
            "train_ids": splits["train"]["frame_names"],
            "val_ids": splits["val"]["frame_names"],
        },
    )
    write_json(root / "metadata.json", metadata)
    write_json(root / "markers.json", markers)
    write_json(root / "scene.json", {"center": [0.0, 0.0, 0.0], "far": 4.0, "near": 0.1, "scale": 0.5})
    write_json(
        root / "extra.json",
        {"factor": scale, "fps": 30.0, "bbox": [[-1, -1, -1], [1, 1, 1]], "lookat": [0, 0, 0], "up": [0, 0, 1]},
    )
    return root
