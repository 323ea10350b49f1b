"""Gaussians as PLY files in the layout of the original 3DGS code (read by
SuperSplat, nerfstudio / gsplat tools and web viewers), through `plyfile`.

One binary little-endian `vertex` element, one vertex per Gaussian, float32
properties in this order:

    x y z                 mean
    nx ny nz              zeros (3DGS writes unused normals)
    f_dc_0 f_dc_1 f_dc_2  SH DC coefficient: colour = 0.5 + SH_C0 * f_dc
    f_rest_0 ...          higher SH coefficients, 3 * M of them, channel-major
                          (every coefficient of R, then of G, then of B)
    opacity               logit: opacity = sigmoid(.)
    scale_0 scale_1 scale_2   log of the per-axis standard deviations
    rot_0 rot_1 rot_2 rot_3   quaternion w, x, y, z

and, where the export carries motion groups, a last int32 `group_id` that
viewers ignore.
"""

from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..artefact import write_bytes
from ..errors import input_error
from ..sh import num_sh_rest
from .colors import sh_degree_of

VERTEX = "vertex"
GROUP_PROPERTY = "group_id"
SPLAT_ARRAYS = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")  # SplatCloud's float arrays


@dataclass
class SplatCloud:
    """Gaussians as a 3DGS PLY file holds them (float32, group_id int32)."""

    means: np.ndarray  # (N, 3)
    quats: np.ndarray  # (N, 4) wxyz
    log_scales: np.ndarray  # (N, 3)
    opacity_logits: np.ndarray  # (N,)
    sh_dc: np.ndarray  # (N, 3) f_dc
    sh_rest: np.ndarray  # (N, M, 3) f_rest, coefficient-major as mogaf.sh uses them
    group_id: np.ndarray | None = None  # (N,)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        return sh_degree_of(int(self.sh_rest.shape[1]))


def splat_property_names(sh_degree: int) -> list[str]:
    """The float properties of a 3DGS PLY vertex, in file order."""
    rest = [f"f_rest_{i}" for i in range(3 * num_sh_rest(sh_degree))]
    return [
        *("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"),
        *rest,
        "opacity",
        *("scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"),
    ]


def splat_vertices(splats: SplatCloud) -> np.ndarray:
    """The vertex records (a structured array, little-endian) of `splats`."""
    n = len(splats)
    names = splat_property_names(splats.sh_degree)
    columns = np.concatenate(
        [
            np.asarray(splats.means).reshape(n, 3),
            np.zeros((n, 3)),
            np.asarray(splats.sh_dc).reshape(n, 3),
            # 3DGS orders the higher bands channel-major: (N, M, 3) -> (N, 3, M)
            np.asarray(splats.sh_rest).transpose(0, 2, 1).reshape(n, -1),
            np.asarray(splats.opacity_logits).reshape(n, 1),
            np.asarray(splats.log_scales).reshape(n, 3),
            np.asarray(splats.quats).reshape(n, 4),
        ],
        axis=1,
    ).astype("<f4")
    fields = [(name, "<f4") for name in names]
    if splats.group_id is not None:
        fields.append((GROUP_PROPERTY, "<i4"))
    vertices = np.empty(n, dtype=fields)
    for j, name in enumerate(names):
        vertices[name] = columns[:, j]
    if splats.group_id is not None:
        vertices[GROUP_PROPERTY] = np.asarray(splats.group_id).reshape(n)
    return vertices


def splat_ply_bytes(splats: SplatCloud) -> bytes:
    """The PLY file of `splats`, encoded in memory."""
    from plyfile import PlyData, PlyElement  # local: only the export reads and writes PLY files

    buffer = io.BytesIO()
    PlyData([PlyElement.describe(splat_vertices(splats), VERTEX)], text=False, byte_order="<").write(buffer)
    return buffer.getvalue()


def write_splat_ply(path: str | os.PathLike, splats: SplatCloud) -> Path:
    """Write `splats` as a 3DGS PLY file, atomically."""
    return write_bytes(path, splat_ply_bytes(splats))


def _layout_problem(names: list[str]) -> str | None:
    """Why property names are not a 3DGS vertex (None: they are)."""
    rest = sum(name.startswith("f_rest_") for name in names)
    if rest % 3:
        return f"has {rest} f_rest properties, not 3 per SH coefficient"
    try:
        degree = sh_degree_of(rest // 3)
    except ValueError:
        return f"has {rest} f_rest properties, which fit no SH degree"
    expected = splat_property_names(degree)
    if names not in (expected, [*expected, GROUP_PROPERTY]):
        shown = " ".join(names[:12]) + (" ..." if len(names) > 12 else "")
        return f"vertex properties are not the 3DGS layout (got {shown})"
    return None


def read_splat_ply(path: str | os.PathLike) -> SplatCloud:
    """A 3DGS PLY file (the layout of this module) as a SplatCloud; a file
    that is missing, unreadable or in another layout is one line naming it."""
    from plyfile import PlyData, PlyParseError  # local: only the export reads and writes PLY files

    p = Path(path)
    if not p.is_file():
        raise input_error(p, "missing (run the export first)")
    try:
        with open(p, "rb") as fh:
            ply = PlyData.read(fh, mmap=False)
    except (PlyParseError, ValueError, EOFError, UnicodeDecodeError) as exc:
        raise input_error(p, f"not a readable PLY file ({exc.__class__.__name__})") from None
    except OSError as exc:
        raise input_error(p, f"cannot be read ({exc.strerror or exc.__class__.__name__})") from None
    if VERTEX not in [el.name for el in ply.elements]:
        raise input_error(p, "has no vertex element")
    element = ply[VERTEX]
    names = [prop.name for prop in element.properties]
    problem = _layout_problem(names)
    if problem is not None:
        raise input_error(p, problem)
    data = element.data
    n = int(data.shape[0])

    def columns(*keys: str) -> np.ndarray:
        return np.stack([np.asarray(data[k], np.float32) for k in keys], axis=1) if keys else np.zeros((n, 0))

    floats = columns(*[name for name in names if name != GROUP_PROPERTY])
    if not np.all(np.isfinite(floats)):
        raise input_error(p, "holds non-finite values")
    rest_names = [name for name in names if name.startswith("f_rest_")]
    m = len(rest_names) // 3
    return SplatCloud(
        means=columns("x", "y", "z"),
        quats=columns("rot_0", "rot_1", "rot_2", "rot_3"),
        log_scales=columns("scale_0", "scale_1", "scale_2"),
        opacity_logits=np.asarray(data["opacity"], np.float32),
        sh_dc=columns("f_dc_0", "f_dc_1", "f_dc_2"),
        sh_rest=columns(*rest_names).reshape(n, 3, m).transpose(0, 2, 1).astype(np.float32),
        group_id=np.asarray(data[GROUP_PROPERTY], np.int32) if GROUP_PROPERTY in names else None,
    )
