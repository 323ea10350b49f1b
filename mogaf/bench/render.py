"""Benchmark of mogaf.render.rasterize on CPU: `python -m mogaf.bench render`.

Reference scene (issue 3): N Gaussians seen head-on by an identity camera,
centres uniform over the image, 2D footprint standard deviations uniform in
0.5-3.5 px with a random orientation, opacities uniform in 0.05-0.95, random
colours and depths in [2, 6]. Methods, timed side by side in one process:

- cpu:       mogaf's C++ kernel (fused projection + tile compositor)
- torch:     mogaf's pure-torch fallback (packed pairs, analytic backward)
- baseline:  the straightforward packed-pairs rasterizer of the issue (torch
             autograd through pairs in the 3.33-sigma box, sort by pixel then
             depth, float64 segmented cumsum of log(1 - alpha), index_add)
- reference: the dense all-Gaussians x all-pixels reference (where it fits)

Times are the median (and min) over repeats of a forward pass (inputs require
grad) and of forward + backward of a loss on colour, depth and alpha; after a
warm-up the methods run round-robin, so load changes on a shared machine hit
them alike. Peak
memory: the peak of torch's CPU allocations during one forward + backward (all
the kernel's large buffers are torch tensors), from the profiler's memory
timeline; where that private API fails, the growth of the peak resident set.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import statistics
import sys
import time

import torch

from mogaf.allocator import set_thresholds
from mogaf.render import cpu, rasterize
from mogaf.render.projection import project_gaussians

LOG_T_MIN = math.log(1e-4)


def reference_scene(n: int, width: int, height: int, seed: int = 0, dtype=torch.float32):
    """(means, quats, scales, opacities, colors, viewmat, K) of the reference scene."""
    g = torch.Generator().manual_seed(seed)
    f = float(max(width, height))
    u = torch.rand(n, generator=g, dtype=torch.float64) * width
    v = torch.rand(n, generator=g, dtype=torch.float64) * height
    z = 2 + 4 * torch.rand(n, generator=g, dtype=torch.float64)
    means = torch.stack([(u - width / 2) * z / f, (v - height / 2) * z / f, z], -1)
    sig = 0.5 + 3.0 * torch.rand(n, 2, generator=g, dtype=torch.float64)
    scales = torch.cat([sig * z[:, None] / f, 1e-3 * z[:, None] / f], -1)
    th = torch.rand(n, generator=g, dtype=torch.float64) * math.pi
    zero = torch.zeros(n, dtype=torch.float64)
    quats = torch.stack([torch.cos(th / 2), zero, zero, torch.sin(th / 2)], -1)
    opac = 0.05 + 0.9 * torch.rand(n, generator=g, dtype=torch.float64)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]], dtype=torch.float64)
    viewmat = torch.eye(4, dtype=torch.float64)
    return tuple(t.to(dtype) for t in (means, quats, scales, opac, colors, viewmat, K))


def straightforward(means, quats, scales, opacities, features, viewmat, K, width, height):
    """The issue's straightforward packed-pairs rasterizer (plain autograd); returns (features, alpha, depth)."""
    proj = project_gaussians(means, quats, scales, opacities, viewmat, K, width, height)
    idx = proj.visible.nonzero().squeeze(1)
    M = idx.numel()
    m2 = proj.means2d[idx]
    con = proj.conics[idx]
    o = opacities[idx]
    z = proj.depths[idx]
    f = torch.cat([features[idx], z[:, None]], 1)
    C = f.shape[1]
    with torch.no_grad():
        rank = torch.empty(M, dtype=torch.long)
        rank[torch.argsort(z, stable=True)] = torch.arange(M)
        det = con[:, 0] * con[:, 2] - con[:, 1] ** 2
        rx = torch.ceil(3.33 * torch.sqrt(con[:, 2] / det))
        ry = torch.ceil(3.33 * torch.sqrt(con[:, 0] / det))
        x0 = torch.clamp(torch.floor(m2[:, 0] - rx), 0, width - 1).long()
        x1 = torch.clamp(torch.floor(m2[:, 0] + rx), 0, width - 1).long()
        y0 = torch.clamp(torch.floor(m2[:, 1] - ry), 0, height - 1).long()
        y1 = torch.clamp(torch.floor(m2[:, 1] + ry), 0, height - 1).long()
        w, h = x1 - x0 + 1, y1 - y0 + 1
        counts = w * h
        g = torch.repeat_interleave(torch.arange(M), counts)
        local = torch.arange(g.numel()) - (torch.cumsum(counts, 0) - counts)[g]
        px = x0[g] + local % w[g]
        py = y0[g] + local // w[g]
    dx = m2[g, 0] - (px + 0.5)
    dy = m2[g, 1] - (py + 0.5)
    a, b, c = con[g, 0], con[g, 1], con[g, 2]
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    alpha = torch.clamp(o[g] * torch.exp(-sigma), max=0.99)
    keep = (alpha >= 1.0 / 255.0).nonzero().squeeze(1)
    alpha, g, pix = alpha[keep], g[keep], (py * width + px)[keep]
    key = pix * max(M, 1) + rank[g]
    _, perm = torch.sort(key)
    alpha, g, pix = alpha[perm], g[perm], pix[perm]
    log1m = torch.log1p(-alpha.double())
    cs = torch.cumsum(log1m, 0)
    cnt = torch.bincount(pix, minlength=width * height)
    start = torch.cumsum(cnt, 0) - cnt
    excl = cs - log1m
    log_t = excl - excl[start[pix]]
    alive = (log_t + log1m > LOG_T_MIN).to(alpha.dtype)
    wgt = alpha * torch.exp(log_t).to(alpha.dtype) * alive
    acc = torch.zeros(width * height, C, dtype=alpha.dtype).index_add(0, pix, wgt[:, None] * f[g])
    log_tf = torch.zeros(width * height, dtype=torch.float64).index_add(0, pix, log1m * alive)
    alpha_img = (1 - torch.exp(log_tf)).to(alpha.dtype).reshape(height, width, 1)
    acc = acc.reshape(height, width, C)
    return acc[..., : C - 1], alpha_img, acc[..., C - 1 :] / alpha_img.clamp(min=1e-10)


def _render(method, inputs, width, height):
    if method == "baseline":
        return straightforward(*inputs, width, height)
    out = rasterize(*inputs, width, height, backend=method)
    return out.features, out.alpha, out.depth


def _loss(outs):
    feats, alpha, depth = outs
    return feats.sum() + 0.1 * depth.sum() + alpha.sum()


def _status_kib(key: str) -> int | None:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(key):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


@contextlib.contextmanager
def _quiet_stderr():
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _peak_profiler(fn) -> float | None:
    """Peak of torch's CPU allocations during fn, from the profiler's memory timeline."""
    try:
        from torch.profiler._memory_profiler import MemoryProfileTimeline

        acts = [torch.profiler.ProfilerActivity.CPU]
        with _quiet_stderr():  # the profiler logs start/stop lines on stderr
            with torch.profiler.profile(
                activities=acts, profile_memory=True, record_shapes=True, with_stack=True
            ) as prof:
                fn()
        _, sizes = MemoryProfileTimeline(prof._memory_profile())._coalesce_timeline(torch.device("cpu"))
        totals = [sum(s) for s in sizes]
        return (max(totals) - totals[0]) / 2**20 if totals else 0.0
    except Exception:  # private API: fall back to the resident set
        return None


def _peak_rss(fn) -> float | None:
    before = _status_kib("VmRSS")
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
    except OSError:
        return None
    fn()
    after = _status_kib("VmHWM")
    if before is None or after is None:
        return None
    return max(0.0, (after - before) / 1024.0)


def peak_mib(fn) -> float | None:
    """Peak extra memory (MiB) of fn: torch allocations (profiler), else peak-RSS growth (Linux)."""
    peak = _peak_profiler(fn)
    return peak if peak is not None else _peak_rss(fn)


class _Runner:
    """One method on its own copy of the reference scene."""

    def __init__(self, method, n, width, height, seed=0):
        self.method, self.width, self.height = method, width, height
        scene = reference_scene(n, width, height, seed)
        self.params = [t.clone().requires_grad_() for t in scene[:5]]
        self.inputs = (*self.params, scene[5], scene[6])
        self.fwd_ms: list[float] = []
        self.fb_ms: list[float] = []

    def fwd(self):
        return _render(self.method, self.inputs, self.width, self.height)

    def fwd_bwd(self):
        for p in self.params:
            p.grad = None
        _loss(self.fwd()).backward()

    def time_once(self):
        t0 = time.perf_counter()
        out = self.fwd()
        self.fwd_ms.append((time.perf_counter() - t0) * 1e3)
        del out
        t0 = time.perf_counter()
        self.fwd_bwd()
        self.fb_ms.append((time.perf_counter() - t0) * 1e3)

    def result(self, with_memory=True):
        return {
            "fwd_med": statistics.median(self.fwd_ms),
            "fwd_min": min(self.fwd_ms),
            "fb_med": statistics.median(self.fb_ms),
            "fb_min": min(self.fb_ms),
            "peak_mib": peak_mib(self.fwd_bwd) if with_memory else None,
        }


def time_methods(methods, n, width, height, repeats, seed=0, reference_repeats=2):
    """Time the methods side by side: after a warm-up, repeats run round-robin
    (so that a load change on a shared machine hits every method alike)."""
    runners = {m: _Runner(m, n, width, height, seed) for m in methods}
    for r in runners.values():
        r.fwd_bwd()  # warm-up (and, for "cpu", the one-off kernel build)
    for i in range(repeats):
        for m, r in runners.items():
            if m != "reference" or i < reference_repeats:
                r.time_once()
    return {m: r.result() for m, r in runners.items()}


def reference_fits(n: int, width: int, height: int, budget_gib: float) -> bool:
    # Measured: the dense forward + backward peaks at ~70 bytes per (Gaussian, pixel) in float32.
    return n * width * height * 72 <= budget_gib * 2**30


def _positive_ints(ap: argparse.ArgumentParser, flag: str, text: str) -> list[int]:
    try:
        values = [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        values = []
    if not values or min(values) < 1:
        ap.error(f"{flag} takes whole numbers >= 1 separated by commas, got {text!r}")
    return values


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m mogaf.bench render", description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="2000,5000,20000,50000", help="comma-separated N")
    ap.add_argument("--res", default="128,256", help="comma-separated square image sizes")
    ap.add_argument("--methods", default="baseline,cpu,torch,reference", help="comma-separated methods")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--reference-gib", type=float, default=3.0, help="memory budget for the dense reference")
    args = ap.parse_args(argv)
    sizes, res = (_positive_ints(ap, flag, text) for flag, text in (("--sizes", args.sizes), ("--res", args.res)))
    if args.repeats < 1:
        ap.error(f"--repeats must be at least 1, got {args.repeats}")
    if args.threads:
        torch.set_num_threads(args.threads)
    # glibc returns freed large blocks to the system, so that the resident set
    # (peak_mib's fallback) tracks live memory; it replaces the stages' settings
    set_thresholds(128 * 1024, 128 * 1024)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    print(
        f"# mogaf.render benchmark: torch {torch.__version__}, {torch.get_num_threads()} threads, "
        f"C++ kernel {'available' if cpu.available() else 'unavailable (' + str(cpu._state['error']) + ')'}"
    )
    print("# times in ms: median (min) over repeats; fwd = forward only, f+b = forward + backward;")
    print("# f+b/baseline: ratio of the min f+b times; peak MiB: extra memory of one forward + backward")
    header = f"{'N':>6} {'res':>5} {'method':<10} {'fwd ms':>17} {'f+b ms':>17} {'peak MiB':>9} {'f+b/baseline':>13}"
    print(header)
    print("-" * len(header))
    for W in res:
        for n in sizes:
            run = []
            for m in methods:
                if m == "reference" and not reference_fits(n, W, W, args.reference_gib):
                    print(f"{n:>6} {W:>4}² {m:<10} {'(does not fit in ' + str(args.reference_gib) + ' GiB)':>36}")
                elif m == "cpu" and not cpu.available():
                    print(f"{n:>6} {W:>4}² {m:<10} {'(kernel unavailable)':>36}")
                else:
                    run.append(m)
            rows = time_methods(run, n, W, W, args.repeats)
            for m, r in rows.items():
                rel = ""
                if "baseline" in rows and m != "baseline":
                    rel = f"{r['fb_min'] / rows['baseline']['fb_min']:.3f}x"
                mem = "n/a" if r["peak_mib"] is None else f"{r['peak_mib']:.1f}"
                print(
                    f"{n:>6} {W:>4}² {m:<10} {r['fwd_med']:>8.1f} ({r['fwd_min']:>6.1f}) "
                    f"{r['fb_med']:>8.1f} ({r['fb_min']:>6.1f}) {mem:>9} {rel:>13}",
                    flush=True,
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
