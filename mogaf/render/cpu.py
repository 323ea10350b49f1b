"""The "cpu" backend: C++ projection and tile compositor, loaded with ctypes.

Two autograd Functions with analytic backward passes:
- `project_cpu`: fused EWA projection (the mathematics of projection.py);
- `composite_cpu`: depth-sorted tile compositing, plus the background and the
  alpha-normalised depth, so that a render is four C calls and almost no torch op
  (small torch ops are slow when their thread pool competes for busy cores).

The kernel (csrc/rasterize.cpp) is plain C++17 with std::thread and no torch
headers, so it compiles in ~10 s with `g++ -O3` (no -march=native: the cache may
be shared between machines; on x86-64 GCC adds an AVX2 clone picked at load
time, and -ffp-contract=off keeps the forward and backward passes bitwise
consistent; no -ffast-math). Threads: mogaf.cores (torch's count, or the idle
cores). The shared object lives in `cache_dir("kernels")`, built by
mogaf.kernel_build (torch-free: `make setup` builds it while torch installs).
Any failure (no compiler, compile error, load error) gives one warning and
`load()` returns None: callers fall back to the torch compositor. Nothing is
built at import time.
"""

from __future__ import annotations

import ctypes
import functools
import threading
import warnings

import torch
from torch.autograd.function import once_differentiable

from mogaf.cores import kernel_threads
from mogaf.errors import MogafError
from mogaf.kernel_build import ABI_VERSION, build, compiler, library_path
from mogaf.timing import KERNELS

DEFAULT_TILE = 32

_lock = threading.Lock()
_state: dict = {"lib": None, "tried": False, "error": None}

_P = ctypes.c_void_p
_I = ctypes.c_int
_L = ctypes.c_int64


def _declare(lib: ctypes.CDLL) -> None:
    for suf in ("f32", "f64"):
        fn = getattr(lib, f"mogaf_splat_bytes_{suf}")
        fn.restype = _L
        fn.argtypes = [_L]
        fn = getattr(lib, f"mogaf_prepare_{suf}")
        fn.restype = _L
        fn.argtypes = [_L, _I, _I, _I, _I] + [_P] * 8 + [_I, _P]
        fn = getattr(lib, f"mogaf_fill_{suf}")
        fn.restype = _I
        fn.argtypes = [_L, _I, _I, _I, _I, _P, _P, _I, _P, _P]
        fn = getattr(lib, f"mogaf_forward_{suf}")
        fn.restype = _I
        fn.argtypes = [_L, _I, _I, _I, _I, _I] + [_P] * 12
        fn = getattr(lib, f"mogaf_backward_{suf}")
        fn.restype = _I
        fn.argtypes = [_L, _I, _I, _I, _I, _I] + [_P] * 18
        fn = getattr(lib, f"mogaf_project_{suf}")
        fn.restype = _I
        fn.argtypes = [_L, _P, _P, _P, _P, _P, _I, _I, ctypes.c_double, ctypes.c_double, ctypes.c_double, _I] + [_P] * 5
        fn = getattr(lib, f"mogaf_project_backward_{suf}")
        fn.restype = _I
        fn.argtypes = [_L, _P, _P, _P, _P, _I, _I, ctypes.c_double, ctypes.c_double, ctypes.c_double, _I] + [_P] * 8
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
            cxx = compiler()
            if cxx is None:
                raise RuntimeError("no C++ compiler found (set CXX or install g++)")
            target = library_path(cxx)
            if not target.exists():
                with KERNELS.phase("kernel_build"):
                    build(cxx, target)
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


def _timed(name: str):
    """Adds each call's time to mogaf.timing.KERNELS[name] (the training loops' breakdown)."""

    def wrap(fn):
        @functools.wraps(fn)
        def timed(*args, **kwargs):
            with KERNELS.phase(name):
                return fn(*args, **kwargs)

        return timed

    return wrap


class _CPURaster(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, depths, radii, background, width, height, tile):
        lib = load()
        if lib is None:
            raise MogafError("mogaf.render: the C++ CPU kernel is unavailable; use backend='torch'")
        dtype = means2d.dtype
        suf = _suffix(dtype)
        ctx.set_materialize_grads(False)
        means2d, conics, opacities, features = (t.contiguous() for t in (means2d, conics, opacities, features))
        radii = radii.to(torch.int32).contiguous()
        depths = depths.to(dtype).contiguous()
        bg = None if background is None else background.detach().to(dtype).reshape(-1).contiguous()
        M, C = features.shape
        NC = C + 1
        if bg is not None and bg.numel() != C:
            bg = bg.expand(C).contiguous()
        ntiles = ((width + tile - 1) // tile) * ((height + tile - 1) // tile)
        nthreads = kernel_threads()
        splats = torch.empty(int(getattr(lib, f"mogaf_splat_bytes_{suf}")(M)), dtype=torch.uint8)
        order = torch.empty(M, dtype=torch.int32)
        offsets = torch.empty(ntiles + 1, dtype=torch.int64)
        nch = min(32, 8 * nthreads) if M >= 8192 else 1  # binning chunks (dynamic scheduling)
        cursors = torch.empty(nch, ntiles, dtype=torch.int64)
        total = getattr(lib, f"mogaf_prepare_{suf}")(
            M, width, height, tile, nthreads, _ptr(means2d), _ptr(conics), _ptr(opacities), _ptr(radii),
            _ptr(depths), _ptr(splats), _ptr(order), _ptr(offsets), nch, _ptr(cursors),
        )  # fmt: skip
        _check(total, "binning")
        if total >= 2**31 - 1:
            raise MogafError(f"mogaf.render: {total} tile intersections exceed the kernel's int32 indices")
        isect = torch.empty(total, dtype=torch.int32)
        rc = getattr(lib, f"mogaf_fill_{suf}")(
            M, width, height, tile, nthreads, _ptr(splats), _ptr(order), nch, _ptr(cursors), _ptr(isect)
        )
        _check(rc, "binning")
        feat = torch.empty(height, width, C, dtype=dtype)
        alpha = torch.empty(height, width, 1, dtype=dtype)
        depth = torch.empty(height, width, 1, dtype=dtype)
        Tf = torch.empty(height, width, dtype=dtype)
        accD = torch.empty(height, width, dtype=dtype)
        last = torch.empty(height, width, dtype=torch.int32)
        rc = getattr(lib, f"mogaf_forward_{suf}")(
            M, NC, width, height, tile, nthreads, _ptr(splats), _ptr(features), _ptr(depths), _ptr(bg),
            _ptr(offsets), _ptr(isect), _ptr(feat), _ptr(alpha), _ptr(depth), _ptr(Tf), _ptr(accD), _ptr(last),
        )  # fmt: skip
        _check(rc, "forward")
        ctx.save_for_backward(features, depths, bg, splats, offsets, isect, Tf, accD, last)
        ctx.dims = (width, height, tile, background is not None and background.requires_grad)
        return feat, alpha, depth

    @staticmethod
    @_timed("raster_backward")
    @once_differentiable
    def backward(ctx, g_feat, g_alpha, g_depth):
        features, depths, bg, splats, offsets, isect, Tf, accD, last = ctx.saved_tensors
        width, height, tile, bg_grad = ctx.dims
        nthreads = kernel_threads()
        dtype = features.dtype
        suf = _suffix(dtype)
        M, C = features.shape
        NC = C + 1
        # Undefined output gradients (outputs not used by the loss) are passed as null (zero).
        g_feat, g_alpha, g_depth = (None if g is None else g.to(dtype).contiguous() for g in (g_feat, g_alpha, g_depth))
        pair = torch.empty(isect.numel(), 6 + NC, dtype=dtype)
        gm = torch.empty(M, 2, dtype=dtype)
        gc = torch.empty(M, 3, dtype=dtype)
        go = torch.empty(M, dtype=dtype)
        gf = torch.empty(M, C, dtype=dtype)
        gz = torch.empty(M, dtype=dtype)
        rc = getattr(load(), f"mogaf_backward_{suf}")(
            M, NC, width, height, tile, nthreads, _ptr(splats), _ptr(features), _ptr(depths), _ptr(bg),
            _ptr(offsets), _ptr(isect), _ptr(Tf), _ptr(accD), _ptr(last), _ptr(g_feat), _ptr(g_alpha), _ptr(g_depth),
            _ptr(pair), _ptr(gm), _ptr(gc), _ptr(go), _ptr(gf), _ptr(gz),
        )  # fmt: skip
        _check(rc, "backward")
        g_bg = None
        if bg_grad and g_feat is not None:
            g_bg = (g_feat * Tf[..., None]).sum((0, 1))
        return gm, gc, go, gf, gz, None, g_bg, None, None, None


def composite_cpu(
    means2d, conics, opacities, features, depths, radii, width, height, background=None, tile=DEFAULT_TILE
):
    """C++ tile compositor: (features (H, W, C), alpha (H, W, 1), depth (H, W, 1)).

    `depths` (M,) orders the Gaussians front to back and is composited as an
    extra channel: `depth` is its alpha-normalised sum (differentiable). The
    features get `background` (C values or one) composited. Gaussians with radii
    (0, 0) are skipped.
    """
    load()  # a first call compiles the kernel: timed as kernel_build, not as compositing
    with KERNELS.phase("raster_forward"):
        return _CPURaster.apply(means2d, conics, opacities, features, depths, radii, background, width, height, tile)


def _suffix(dtype: torch.dtype) -> str:
    suf = {torch.float32: "f32", torch.float64: "f64"}.get(dtype)
    if suf is None:
        raise MogafError(f"mogaf.render: the CPU kernel supports float32 and float64, not {dtype}")
    return suf


def _camera(viewmat: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    Kd = K.detach().to(torch.float64).reshape(-1)
    return torch.cat([viewmat.detach().to(torch.float64).reshape(-1), Kd[[0, 4, 2, 5]]]).contiguous()


class _ProjectCPU(torch.autograd.Function):
    """Fused EWA projection (csrc/rasterize.cpp), same mathematics as projection.project_gaussians."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmat, K, width, height, near, far, eps2d):
        lib = load()
        if lib is None:
            raise MogafError("mogaf.render: the C++ CPU kernel is unavailable; use backend='torch'")
        dtype = means.dtype
        suf = _suffix(dtype)
        means, quats, scales = (t.to(dtype).contiguous() for t in (means, quats, scales))
        opacities = opacities.to(dtype).contiguous()
        cam = _camera(viewmat, K)
        N = means.shape[0]
        nthreads = kernel_threads()
        means2d = torch.empty(N, 2, dtype=dtype)
        conics = torch.empty(N, 3, dtype=dtype)
        depths = torch.empty(N, dtype=dtype)
        radii = torch.empty(N, 2, dtype=torch.int32)
        visible = torch.empty(N, dtype=torch.bool)
        rc = getattr(lib, f"mogaf_project_{suf}")(
            N, _ptr(means), _ptr(quats), _ptr(scales), _ptr(opacities), _ptr(cam), width, height,
            float(near), float(far), float(eps2d), nthreads, _ptr(means2d), _ptr(conics), _ptr(depths), _ptr(radii),
            _ptr(visible),
        )  # fmt: skip
        _check(rc, "projection")
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(means, quats, scales, cam, radii)
        ctx.dims = (width, height, float(near), float(far), float(eps2d), viewmat.dtype)
        ctx.mark_non_differentiable(radii, visible)
        return means2d, conics, depths, radii, visible

    @staticmethod
    @_timed("raster_backward")
    @once_differentiable
    def backward(ctx, g_means2d, g_conics, g_depths, _g_radii, _g_visible):
        means, quats, scales, cam, radii = ctx.saved_tensors
        width, height, near, far, eps2d, view_dtype = ctx.dims
        nthreads = kernel_threads()
        dtype = means.dtype
        suf = _suffix(dtype)
        N = means.shape[0]
        g_means2d, g_conics, g_depths = (
            None if g is None else g.to(dtype).contiguous() for g in (g_means2d, g_conics, g_depths)
        )
        gm = torch.empty(N, 3, dtype=dtype)
        gq = torch.empty(N, 4, dtype=dtype)
        gs = torch.empty(N, 3, dtype=dtype)
        want_view = ctx.needs_input_grad[4]
        gv = torch.zeros(16, dtype=torch.float64) if want_view else None
        rc = getattr(load(), f"mogaf_project_backward_{suf}")(
            N, _ptr(means), _ptr(quats), _ptr(scales), _ptr(cam), width, height, near, far, eps2d, nthreads,
            _ptr(radii), _ptr(g_means2d), _ptr(g_conics), _ptr(g_depths), _ptr(gm), _ptr(gq), _ptr(gs), _ptr(gv),
        )  # fmt: skip
        _check(rc, "projection backward")
        g_view = gv.reshape(4, 4).to(view_dtype) if want_view else None
        return gm, gq, gs, None, g_view, None, None, None, None, None, None


def project_cpu(means, quats, scales, opacities, viewmat, K, width, height, near=0.01, far=1e10, eps2d=0.3):
    """(means2d (N, 2), conics (N, 3), depths (N,), radii (N, 2) int32, visible (N,) bool), fused C++."""
    load()  # a first call compiles the kernel: timed as kernel_build, not as projection
    with KERNELS.phase("raster_forward"):
        return _ProjectCPU.apply(means, quats, scales, opacities, viewmat, K, width, height, near, far, eps2d)
