"""The C++ CPU compositor: build once with the system compiler, load with ctypes.

The kernel (csrc/rasterize.cpp) is plain C++17 with std::thread and no torch
headers, so it compiles in a few seconds with `g++ -O3` (no -march=native: the
cache may be shared between machines). The shared object lives in
`cache_dir("kernels")` under a name that hashes the source, the flags, the
compiler and the machine type; it is built into a temporary file and renamed, so
concurrent processes may build at once. Any failure (no compiler, compile error,
load error) gives one warning and `load()` returns None: callers fall back to the
torch compositor. Nothing is built at import time.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
import warnings
from pathlib import Path

import torch
from torch.autograd.function import once_differentiable

from mogaf.errors import MogafError
from mogaf.paths import cache_dir

SOURCE = Path(__file__).with_name("csrc") / "rasterize.cpp"
ABI_VERSION = 2
BASE_FLAGS = ["-O3", "-std=c++17", "-shared", "-fPIC", "-pthread", "-ffp-contract=off", "-fno-math-errno", "-Wno-psabi"]
# Static libstdc++ keeps the .so loadable on machines sharing the cache; dropped if unavailable.
STATIC_FLAGS = ["-static-libstdc++", "-static-libgcc"]
DEFAULT_TILE = 16

_lock = threading.Lock()
_state: dict = {"lib": None, "tried": False, "error": None}

_P = ctypes.c_void_p
_I = ctypes.c_int
_L = ctypes.c_int64


def _compiler() -> str | None:
    for cand in (os.environ.get("CXX"), "g++", "c++", "clang++"):
        if cand and shutil.which(cand):
            return shutil.which(cand)
    return None


def library_path(cxx: str) -> Path:
    h = hashlib.sha256()
    h.update(SOURCE.read_bytes())
    h.update(repr((BASE_FLAGS, STATIC_FLAGS, os.path.basename(cxx), platform.machine(), ABI_VERSION)).encode())
    return cache_dir("kernels") / f"mogaf_raster_{h.hexdigest()[:16]}.so"


def _build(cxx: str, target: Path) -> None:
    errors = []
    for extra in (STATIC_FLAGS, []):
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
        os.close(fd)
        try:
            cmd = [cxx, *BASE_FLAGS, *extra, str(SOURCE), "-o", tmp]
            res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
            if res.returncode == 0:
                os.chmod(tmp, 0o755)
                os.replace(tmp, target)
                return
            errors.append(res.stderr.strip().splitlines()[-1:] or ["(no output)"])
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    raise RuntimeError(f"{os.path.basename(cxx)} failed: {errors[-1][0]}")


def _declare(lib: ctypes.CDLL) -> None:
    for suf in ("f32", "f64"):
        fn = getattr(lib, f"mogaf_splat_bytes_{suf}")
        fn.restype = _L
        fn.argtypes = [_L]
        fn = getattr(lib, f"mogaf_prepare_{suf}")
        fn.restype = _L
        fn.argtypes = [_L, _I, _I, _I, _I] + [_P] * 8
        fn = getattr(lib, f"mogaf_fill_{suf}")
        fn.restype = _I
        fn.argtypes = [_L, _I, _I, _I] + [_P] * 4
        fn = getattr(lib, f"mogaf_forward_{suf}")
        fn.restype = _I
        fn.argtypes = [_L, _I, _I, _I, _I, _I] + [_P] * 7
        fn = getattr(lib, f"mogaf_backward_{suf}")
        fn.restype = _I
        fn.argtypes = [_L, _I, _I, _I, _I, _I] + [_P] * 13
    lib.mogaf_raster_abi_version.restype = _I
    lib.mogaf_raster_abi_version.argtypes = []


def load(warn: bool = True) -> ctypes.CDLL | None:
    """The compiled kernel library, building it on first use; None if unavailable."""
    if _state["tried"]:
        return _state["lib"]
    with _lock:
        if _state["tried"]:
            return _state["lib"]
        lib = None
        try:
            cxx = _compiler()
            if cxx is None:
                raise RuntimeError("no C++ compiler found (set CXX or install g++)")
            target = library_path(cxx)
            if not target.exists():
                _build(cxx, target)
            lib = ctypes.CDLL(str(target))
            _declare(lib)
            if lib.mogaf_raster_abi_version() != ABI_VERSION:
                raise RuntimeError(f"{target} has an unexpected ABI version")
        except Exception as exc:  # any failure means: use the torch compositor
            lib = None
            _state["error"] = f"{type(exc).__name__}: {exc}"
            if warn:
                warnings.warn(
                    f"mogaf.render: the C++ CPU kernel is unavailable ({_state['error']}); "
                    "using the slower pure-torch compositor",
                    RuntimeWarning,
                    stacklevel=3,
                )
        _state["lib"] = lib
        _state["tried"] = True
        return lib


def available() -> bool:
    return load(warn=False) is not None


def _ptr(t: torch.Tensor | None) -> int | None:
    return None if t is None else t.data_ptr()


def _check(rc: int, what: str) -> None:
    if rc == -1:
        raise MemoryError(f"mogaf.render: out of memory in the CPU kernel ({what})")
    if rc < 0:
        raise MogafError(f"mogaf.render: the CPU kernel failed in {what} (code {rc})")


class _CPURaster(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, feats, radii, depths, width, height, tile):
        lib = load()
        if lib is None:
            raise MogafError("mogaf.render: the C++ CPU kernel is unavailable; use backend='torch'")
        dtype = means2d.dtype
        suf = {torch.float32: "f32", torch.float64: "f64"}.get(dtype)
        if suf is None:
            raise MogafError(f"mogaf.render: the CPU kernel supports float32 and float64, not {dtype}")
        means2d, conics, opacities, feats = (t.contiguous() for t in (means2d, conics, opacities, feats))
        radii = radii.to(torch.int32).contiguous()
        depths = depths.to(dtype).contiguous()
        M, NC = feats.shape
        ntiles = ((width + tile - 1) // tile) * ((height + tile - 1) // tile)
        nthreads = max(1, torch.get_num_threads())
        splats = torch.empty(int(getattr(lib, f"mogaf_splat_bytes_{suf}")(M)), dtype=torch.uint8)
        order = torch.empty(M, dtype=torch.int32)
        offsets = torch.empty(ntiles + 1, dtype=torch.int64)
        total = getattr(lib, f"mogaf_prepare_{suf}")(
            M, width, height, tile, nthreads, _ptr(means2d), _ptr(conics), _ptr(opacities), _ptr(radii),
            _ptr(depths), _ptr(splats), _ptr(order), _ptr(offsets),
        )  # fmt: skip
        _check(total, "binning")
        if total >= 2**31 - 1:
            raise MogafError(f"mogaf.render: {total} tile intersections exceed the kernel's int32 indices")
        isect = torch.empty(total, dtype=torch.int32)
        rc = getattr(lib, f"mogaf_fill_{suf}")(M, width, height, tile, _ptr(splats), _ptr(order), _ptr(offsets), _ptr(isect))
        _check(rc, "binning")
        acc = torch.empty(height, width, NC, dtype=dtype)
        Tf = torch.empty(height, width, dtype=dtype)
        last = torch.empty(height, width, dtype=torch.int32)
        rc = getattr(lib, f"mogaf_forward_{suf}")(
            M, NC, width, height, tile, nthreads, _ptr(splats), _ptr(feats), _ptr(offsets), _ptr(isect),
            _ptr(acc), _ptr(Tf), _ptr(last),
        )  # fmt: skip
        _check(rc, "forward")
        ctx.save_for_backward(feats, splats, offsets, isect, Tf, last)
        ctx.dims = (width, height, tile, nthreads)
        return acc, (1 - Tf).unsqueeze(-1)

    @staticmethod
    @once_differentiable
    def backward(ctx, g_acc, g_alpha):
        feats, splats, offsets, isect, Tf, last = ctx.saved_tensors
        width, height, tile, nthreads = ctx.dims
        dtype = feats.dtype
        suf = "f32" if dtype == torch.float32 else "f64"
        M, NC = feats.shape
        g_acc = g_acc.to(dtype).contiguous()
        g_alpha = g_alpha.to(dtype).reshape(height, width).contiguous()
        pair = torch.empty(isect.numel(), 6 + NC, dtype=dtype)
        gm = torch.empty(M, 2, dtype=dtype)
        gc = torch.empty(M, 3, dtype=dtype)
        go = torch.empty(M, dtype=dtype)
        gf = torch.empty(M, NC, dtype=dtype)
        rc = getattr(load(), f"mogaf_backward_{suf}")(
            M, NC, width, height, tile, nthreads, _ptr(splats), _ptr(feats), _ptr(offsets), _ptr(isect),
            _ptr(Tf), _ptr(last), _ptr(g_acc), _ptr(g_alpha), _ptr(pair), _ptr(gm), _ptr(gc), _ptr(go), _ptr(gf),
        )  # fmt: skip
        _check(rc, "backward")
        return gm, gc, go, gf, None, None, None, None, None


def composite_cpu(means2d, conics, opacities, feats, radii, depths, width, height, tile=DEFAULT_TILE):
    """(acc (H, W, NC), alpha (H, W, 1)) with the C++ tile compositor; depths only order the Gaussians."""
    return _CPURaster.apply(means2d, conics, opacities, feats, radii, depths, width, height, tile)
