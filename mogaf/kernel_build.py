"""Building the CPU rasterizer's C++ kernel (mogaf/render/csrc/rasterize.cpp).

Torch-free and stdlib-only, so that `make setup` can compile the kernel while
pip is still installing torch: `python -m mogaf.kernel_build` builds it into
`cache_dir("kernels")` (MOGAF_CACHE_DIR) where mogaf.render.cpu.load() looks
for it, and prints one line. The library's name hashes the source, the flags,
the compiler and the machine type; it is built into a temporary file and
renamed, so concurrent processes may build at once.
"""

from __future__ import annotations

import hashlib
import os
import platform
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from mogaf.paths import cache_dir

SOURCE = Path(__file__).parent / "render" / "csrc" / "rasterize.cpp"
ABI_VERSION = 6
BASE_FLAGS = ["-O3", "-std=c++17", "-shared", "-fPIC", "-pthread", "-ffp-contract=off", "-fno-math-errno", "-Wno-psabi"]
# Static libstdc++ keeps the .so loadable on machines sharing the cache; dropped if unavailable.
STATIC_FLAGS = ["-static-libstdc++", "-static-libgcc"]


def compiler() -> str | None:
    """The C++ compiler: $CXX, else g++, c++ or clang++ on PATH; None without one."""
    for cand in (os.environ.get("CXX"), "g++", "c++", "clang++"):
        if cand and shutil.which(cand):
            return shutil.which(cand)
    return None


def library_path(cxx: str) -> Path:
    h = hashlib.sha256()
    h.update(SOURCE.read_bytes())
    h.update(repr((BASE_FLAGS, STATIC_FLAGS, os.path.basename(cxx), platform.machine(), ABI_VERSION)).encode())
    return cache_dir("kernels") / f"mogaf_raster_{h.hexdigest()[:16]}.so"


def build(cxx: str, target: Path) -> None:
    """Compile the kernel to `target` (static libstdc++ first, then without); RuntimeError on failure."""
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
            lines = res.stderr.strip().splitlines()
            first_error = [ln for ln in lines if "error" in ln.lower()][:1]
            errors.append(first_error or lines[-1:] or ["(no output)"])
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
    raise RuntimeError(f"{os.path.basename(cxx)} failed: {errors[-1][0]}")


def main() -> int:
    """Build the kernel unless it is built already. Without a compiler, or
    where it fails, say so and exit 0: the pipeline then renders with the
    slower pure-torch compositor (mogaf.render.cpu.load warns again)."""
    cxx = compiler()
    if cxx is None:
        print("mogaf.kernel_build: no C++ compiler found (set CXX or install g++); the torch compositor will be used")
        return 0
    target = library_path(cxx)
    if target.exists():
        print(f"mogaf.kernel_build: {target} is built already")
        return 0
    try:
        build(cxx, target)
    except (RuntimeError, OSError, subprocess.SubprocessError) as exc:
        print(f"mogaf.kernel_build: the kernel did not build ({exc}); the torch compositor will be used")
        return 0
    print(f"mogaf.kernel_build: built {target}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
