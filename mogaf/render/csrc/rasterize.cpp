// Tile-based CPU rasterizer for projected 3D Gaussians (3DGS / EWA compositing)
// with the analytic backward pass.
//
// Plain C++17 + std::thread: no torch headers (they take ~40 s to compile), no
// OpenMP (its runtime is not fork-safe and may be absent). Loaded with ctypes by
// mogaf/render/cpu.py, which owns every large buffer (so torch accounts for memory).
//
// Semantics (identical to mogaf.render.reference.composite_dense):
//   pixel (i, j) has centre (i + 0.5, j + 0.5); Gaussian g touches it iff the
//   centre lies in the closed box |mx - px| <= rx, |my - py| <= ry and
//   alpha = min(0.99, o exp(-sigma)) >= 1/255, with
//   sigma = 0.5 (a dx^2 + c dy^2) + b dx dy (dx = mx - px, dy = my - py; the
//   conic is positive definite by construction). Gaussians are composited front
//   to back by depth (stable: ties by index); a pixel stops at the first Gaussian
//   that would bring its transmittance to <= 1e-4 (that one is not composited),
//   as in 3DGS / gsplat.
//
// Tiles only organise the work: the result does not depend on the tile size.
// Within a tile the loop runs over the tile's depth-sorted Gaussians and, for
// each, over the rows of its box and the columns of its (conservative) alpha >=
// 1/255 ellipse span; per-pixel state lives in small tile arrays. The inner
// loops are branch-free so that GCC vectorises them (SSE2 baseline, plus an AVX2
// clone selected at load time on x86-64). exp is a polynomial (float: ~1 ulp,
// double: ~2 ulp) so that it vectorises; forward and backward use the same code,
// so their per-pair decisions agree exactly.
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <new>
#include <thread>
#include <vector>

#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && !defined(MOGAF_NO_CLONES)
#define MOGAF_CLONES __attribute__((target_clones("avx2", "default")))
#else
#define MOGAF_CLONES
#endif
#if defined(__GNUC__)
#define MOGAF_INLINE __attribute__((always_inline)) inline
#define MOGAF_IVDEP _Pragma("GCC ivdep")
#else
#define MOGAF_INLINE inline
#define MOGAF_IVDEP
#endif

namespace {

constexpr double kAlphaMin = 1.0 / 255.0;
constexpr double kAlphaMax = 0.99;
constexpr double kTMin = 1e-4;
constexpr int kMaxTile = 64;

// ----------------------------------------------------------------------------
// Threads: fn(item, worker) for item in [0, n), items handed out dynamically.
template <typename F>
void parallel_for(int64_t n, int nthreads, F &&fn) {
    if (n <= 0) return;
    if (nthreads > n) nthreads = (int)n;
    if (nthreads <= 1) {
        for (int64_t i = 0; i < n; ++i) fn(i, 0);
        return;
    }
    std::atomic<int64_t> next(0);
    auto worker = [&](int w) {
        for (;;) {
            int64_t i = next.fetch_add(1, std::memory_order_relaxed);
            if (i >= n) break;
            fn(i, w);
        }
    };
    std::vector<std::thread> pool;
    pool.reserve(nthreads - 1);
    for (int t = 1; t < nthreads; ++t) {
        try {
            pool.emplace_back(worker, t);
        } catch (...) {
            break;  // fewer threads is fine
        }
    }
    worker(0);
    for (auto &th : pool) th.join();
}

// Tiles, most intersections first: with dynamic scheduling the last items are the
// cheap ones, so a thread descheduled on a busy machine holds up the join less.
inline std::vector<int64_t> tiles_by_cost(const int64_t *tile_offsets, int64_t ntiles) {
    std::vector<int64_t> ids((size_t)ntiles);
    for (int64_t t = 0; t < ntiles; ++t) ids[(size_t)t] = t;
    std::stable_sort(ids.begin(), ids.end(), [&](int64_t x, int64_t y) {
        return tile_offsets[x + 1] - tile_offsets[x] > tile_offsets[y + 1] - tile_offsets[y];
    });
    return ids;
}

// Threads worth using for n items of roughly `per_item` work units, at least
// `min_per_thread` units each (thread start-up costs ~20-50 us).
inline int threads_for(int64_t units, int64_t min_per_thread, int nthreads) {
    const int64_t k = std::max<int64_t>(1, units / std::max<int64_t>(1, min_per_thread));
    return (int)std::max<int64_t>(1, std::min<int64_t>(nthreads, k));
}

// ----------------------------------------------------------------------------
// Explicit SIMD through GCC/Clang vector extensions (portable: lowered to
// whatever the target has; 32-byte vectors are split in two on SSE2).
template <typename T>
struct VT;
template <>
struct VT<float> {
    static constexpr int V = 8;
    typedef float vT __attribute__((vector_size(32)));
    typedef int32_t vM __attribute__((vector_size(32)));
    typedef int32_t IT;
};
template <>
struct VT<double> {
    static constexpr int V = 4;
    typedef double vT __attribute__((vector_size(32)));
    typedef int64_t vM __attribute__((vector_size(32)));
    typedef int64_t IT;
};

template <typename V>
MOGAF_INLINE V vload(const void *p) {
    V v;
    std::memcpy(&v, p, sizeof(V));
    return v;
}
template <typename V>
MOGAF_INLINE void vstore(void *p, const V &v) {
    std::memcpy(p, &v, sizeof(V));
}
template <typename vT, typename vM>
MOGAF_INLINE vT vsel(vM m, vT a, vT b) {  // m ? a : b, lane-wise (m is all-ones / zero)
    return (vT)(((vM)a & m) | ((vM)b & ~m));
}
template <typename vM>
MOGAF_INLINE vM isel(vM m, vM a, vM b) {
    return (a & m) | (b & ~m);
}

// Branch-free exp(x) for x <= 0 (clamped), lane-wise. float: cephes expf
// polynomial (~1 ulp); double: Taylor to degree 13 on |r| <= ln2 / 2 (~2 ulp).
MOGAF_INLINE VT<float>::vT vexp(VT<float>::vT x) {
    typedef VT<float>::vT vT;
    typedef VT<float>::vM vM;
    const vT lo = vT{} - 87.0f, zero = vT{};
    x = vsel<vT, vM>(x < lo, lo, x);
    x = vsel<vT, vM>(x > zero, zero, x);
    const vT magic = vT{} + 12582912.0f;  // 1.5 * 2^23: adding it rounds to an integer
    const vT t = x * 1.44269504088896341f + magic;
    const vT k = t - magic;
    const vM ki = (vM)t - 0x4B400000;
    vT r = x - k * 0.693359375f;
    r = r - k * -2.12194440e-4f;
    vT p = vT{} + 1.9875691500e-4f;
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    p = p * (r * r) + r + 1.0f;
    const vM bits = (ki + 127) << 23;
    return p * (vT)bits;
}

MOGAF_INLINE VT<double>::vT vexp(VT<double>::vT x) {
    typedef VT<double>::vT vT;
    typedef VT<double>::vM vM;
    const vT lo = vT{} - 708.0, zero = vT{};
    x = vsel<vT, vM>(x < lo, lo, x);
    x = vsel<vT, vM>(x > zero, zero, x);
    const vT magic = vT{} + 6755399441055744.0;  // 1.5 * 2^52
    const vT t = x * 1.4426950408889634074 + magic;
    const vT k = t - magic;
    const vM ki = (vM)t - INT64_C(0x4338000000000000);
    vT r = x - k * 6.93147180369123816490e-01;
    r = r - k * 1.90821492927058770002e-10;
    vT p = vT{} + 1.0 / 6227020800.0;
    p = p * r + 1.0 / 479001600.0;
    p = p * r + 1.0 / 39916800.0;
    p = p * r + 1.0 / 3628800.0;
    p = p * r + 1.0 / 362880.0;
    p = p * r + 1.0 / 40320.0;
    p = p * r + 1.0 / 5040.0;
    p = p * r + 1.0 / 720.0;
    p = p * r + 1.0 / 120.0;
    p = p * r + 1.0 / 24.0;
    p = p * r + 1.0 / 6.0;
    p = p * r + 0.5;
    p = p * (r * r) + r + 1.0;
    const vM bits = (ki + 1023) << 52;
    return p * (vT)bits;
}

template <typename vT, int V>
MOGAF_INLINE vT lane_index() {
    vT v;
    for (int l = 0; l < V; ++l) v[l] = (decltype(v[0] + 0))l;
    return v;
}
// ----------------------------------------------------------------------------
// Per-Gaussian screen-space record, computed once per render and kept (as raw
// bytes owned by Python) for the backward pass.
template <typename T>
struct Splat {
    T mx, my, a, b, c, o;
    double tau;  // relaxed bound on sigma (alpha >= 1/255 implies sigma <= tau)
    double det;  // a c - b^2 of the conic
    double inv_a, two_a_tau, b_over_a;  // row-span helpers
    int32_t i0, i1, j0, j1;  // inclusive pixel box clipped to the image (empty if i0 > i1)
};

template <typename T>
MOGAF_INLINE bool in_box(T m, T r, int i) {
    T d = m - ((T)i + (T)0.5);
    return std::abs(d) <= r;
}

// Pixels i in [0, n) whose centre satisfies |m - (i + 0.5)| <= r, evaluated
// exactly as the torch reference evaluates it.
template <typename T>
inline void box_range(T m, T r, int n, int32_t &lo, int32_t &hi) {
    double md = (double)m, rd = (double)r;
    double flo = std::ceil(md - rd - 0.5), fhi = std::floor(md + rd - 0.5);
    double lim_lo = -4.0, lim_hi = (double)n + 4.0;
    flo = std::min(std::max(flo, lim_lo), lim_hi);
    fhi = std::min(std::max(fhi, lim_lo), lim_hi);
    int l = (int)flo, h = (int)fhi;
    if (in_box(m, r, l - 1)) --l;
    else if (!in_box(m, r, l)) ++l;
    if (in_box(m, r, h + 1)) ++h;
    else if (!in_box(m, r, h)) --h;
    lo = std::max(l, 0);
    hi = std::min(h, n - 1);
}

template <typename T>
inline Splat<T> make_splat(int64_t g, int W, int H, const T *means2d, const T *conics, const T *opac,
                           const int32_t *radii) {
    Splat<T> s;
    s.mx = means2d[2 * g];
    s.my = means2d[2 * g + 1];
    s.a = conics[3 * g];
    s.b = conics[3 * g + 1];
    s.c = conics[3 * g + 2];
    s.o = opac[g];
    s.det = (double)s.a * (double)s.c - (double)s.b * (double)s.b;
    const double o = (double)s.o;
    const bool ok = std::isfinite((double)s.mx) && std::isfinite((double)s.my) && std::isfinite((double)s.a) &&
                    std::isfinite((double)s.b) && std::isfinite((double)s.c) && o * 255.0 >= 1.0 &&
                    radii[2 * g] >= 0 && radii[2 * g + 1] >= 0 && (radii[2 * g] > 0 || radii[2 * g + 1] > 0);
    s.tau = ok ? std::log(255.0 * o) * (1.0 + 1e-4) + 1e-3 : -1.0;
    const double a = (double)s.a;
    s.inv_a = a > 0.0 ? 1.0 / a : 0.0;
    s.two_a_tau = 2.0 * a * s.tau;
    s.b_over_a = (double)s.b * s.inv_a;
    if (!ok) {
        s.i0 = s.j0 = 0;
        s.i1 = s.j1 = -1;
        return s;
    }
    box_range(s.mx, (T)radii[2 * g], W, s.i0, s.i1);
    box_range(s.my, (T)radii[2 * g + 1], H, s.j0, s.j1);
    return s;
}

// Columns of row j (clipped to the box) that may have alpha >= 1/255: the
// centres px with sigma(mx - px, my - py) <= tau, i.e.
// |px - (mx + (b / a) dy)| <= sqrt(2 a tau - det dy^2) / a.
template <typename T>
MOGAF_INLINE bool row_span(const Splat<T> &s, int j, int &ia, int &ib) {
    ia = s.i0;
    ib = s.i1;
    if (ia > ib) return false;
    if (!(s.det > 0.0) || !(s.inv_a > 0.0)) return true;  // degenerate conic: whole box row
    const double dy = (double)s.my - ((double)j + 0.5);
    const double disc = s.two_a_tau - s.det * dy * dy;
    if (disc < 0.0) return false;
    const double hw = std::sqrt(disc) * s.inv_a;
    const double ctr = (double)s.mx + s.b_over_a * dy - 0.5;
    const double lo = std::ceil(ctr - hw);
    const double hi = std::floor(ctr + hw);
    if (lo > (double)ia) ia = (lo > (double)ib) ? ib + 1 : (int)lo;
    if (hi < (double)ib) ib = (hi < (double)ia) ? ia - 1 : (int)hi;
    return ia <= ib;
}

inline double seg_min(double a, double b, double c, double fixed, double lo, double hi, bool fixed_is_dy) {
    // min over the free coordinate in [lo, hi] of 0.5 a dx^2 + b dx dy + 0.5 c dy^2
    if (fixed_is_dy) {
        const double dy = fixed;
        double dx = a > 0.0 ? -b * dy / a : 0.0;
        dx = std::min(std::max(dx, lo), hi);
        return 0.5 * a * dx * dx + b * dx * dy + 0.5 * c * dy * dy;
    }
    const double dx = fixed;
    double dy = c > 0.0 ? -b * dx / c : 0.0;
    dy = std::min(std::max(dy, lo), hi);
    return 0.5 * a * dx * dx + b * dx * dy + 0.5 * c * dy * dy;
}

// Does the relaxed ellipse reach a pixel centre of columns [c0, c1] x rows [r0, r1]?
template <typename T>
inline bool hits_rect(const Splat<T> &s, int c0, int c1, int r0, int r1) {
    if (!(s.det > 0.0)) return true;
    const double mx = (double)s.mx, my = (double)s.my;
    const double dx_lo = mx - ((double)c1 + 0.5), dx_hi = mx - ((double)c0 + 0.5);
    const double dy_lo = my - ((double)r1 + 0.5), dy_hi = my - ((double)r0 + 0.5);
    if (dx_lo <= 0.0 && dx_hi >= 0.0 && dy_lo <= 0.0 && dy_hi >= 0.0) return true;
    const double a = (double)s.a, b = (double)s.b, c = (double)s.c;
    double m = seg_min(a, b, c, dy_lo, dx_lo, dx_hi, true);
    m = std::min(m, seg_min(a, b, c, dy_hi, dx_lo, dx_hi, true));
    m = std::min(m, seg_min(a, b, c, dx_lo, dy_lo, dy_hi, false));
    m = std::min(m, seg_min(a, b, c, dx_hi, dy_lo, dy_hi, false));
    return m <= s.tau * (1.0 + 1e-6) + 1e-6;
}

// Visit the tiles a splat may touch (ellipse-tested), in row-major tile order.
template <typename T, typename F>
inline void for_each_tile(const Splat<T> &s, int TS, int ntx, F &&fn) {
    if (s.i0 > s.i1 || s.j0 > s.j1) return;
    const int tx0 = s.i0 / TS, tx1 = s.i1 / TS, ty0 = s.j0 / TS, ty1 = s.j1 / TS;
    const bool single = (tx0 == tx1 && ty0 == ty1);
    for (int ty = ty0; ty <= ty1; ++ty) {
        const int r0 = std::max(ty * TS, s.j0), r1 = std::min(ty * TS + TS - 1, s.j1);
        for (int tx = tx0; tx <= tx1; ++tx) {
            const int c0 = std::max(tx * TS, s.i0), c1 = std::min(tx * TS + TS - 1, s.i1);
            if (single || hits_rect(s, c0, c1, r0, r1)) fn(ty * ntx + tx);
        }
    }
}

// Stable ascending order by depth (ties by index) of the n Gaussians in idx
// (given in increasing index order); the result overwrites idx.
inline void depth_order(int64_t n, const float *depth, int32_t *idx) {
    // LSD radix sort on order-preserving uint32 keys, 3 passes of 11 bits.
    std::vector<uint32_t> key((size_t)n), key2((size_t)n);
    std::vector<int32_t> tmp((size_t)n);
    for (int64_t i = 0; i < n; ++i) {
        uint32_t u;
        std::memcpy(&u, depth + idx[i], 4);
        key[(size_t)i] = (u & 0x80000000u) ? ~u : (u | 0x80000000u);
    }
    int32_t *src = idx, *dst = tmp.data();
    uint32_t *ksrc = key.data(), *kdst = key2.data();
    for (int shift = 0; shift < 32; shift += 11) {
        std::vector<int64_t> cnt(2049, 0);
        for (int64_t i = 0; i < n; ++i) cnt[((ksrc[i] >> shift) & 2047u) + 1]++;
        for (int d = 0; d < 2048; ++d) cnt[d + 1] += cnt[d];
        for (int64_t i = 0; i < n; ++i) {
            const int64_t pos = cnt[(ksrc[i] >> shift) & 2047u]++;
            dst[pos] = src[i];
            kdst[pos] = ksrc[i];
        }
        std::swap(src, dst);
        std::swap(ksrc, kdst);
    }
    if (src != idx) std::memcpy(idx, src, sizeof(int32_t) * (size_t)n);
}

inline void depth_order(int64_t n, const double *depth, int32_t *idx) {
    std::stable_sort(idx, idx + n, [&](int32_t x, int32_t y) { return depth[x] < depth[y]; });
}

// Binning. The n visible Gaussians, in depth order, are split into nch chunks of
// consecutive ranks; cursors (nch x ntiles, owned by the caller) hold, after
// prepare, where chunk c starts writing in tile t, so that fill runs the chunks
// in parallel and still leaves every tile list in depth order.
template <typename T>
int64_t prepare_impl(int64_t M, int W, int H, int TS, int nthreads, const T *means2d, const T *conics,
                     const T *opac, const int32_t *radii, const T *depths, Splat<T> *splats, int32_t *order,
                     int64_t *tile_offsets, int nch, int64_t *cursors) {
    const int ntx = (W + TS - 1) / TS, nty = (H + TS - 1) / TS;
    const int64_t ntiles = (int64_t)ntx * nty;
    const int64_t chunk = 2048;
    parallel_for((M + chunk - 1) / chunk, threads_for(M, 8192, nthreads), [&](int64_t ci, int) {
        const int64_t g1 = std::min(M, (ci + 1) * chunk);
        for (int64_t g = ci * chunk; g < g1; ++g) splats[g] = make_splat(g, W, H, means2d, conics, opac, radii);
    });
    // Gaussians with an empty box (culled: radii 0, or off the image) are left out.
    int64_t n = 0;
    for (int64_t g = 0; g < M; ++g)
        if (splats[g].i0 <= splats[g].i1 && splats[g].j0 <= splats[g].j1) order[n++] = (int32_t)g;
    for (int64_t r = n; r < M; ++r) order[r] = -1;
    depth_order(n, depths, order);
    std::fill(cursors, cursors + (size_t)nch * ntiles, (int64_t)0);
    parallel_for(nch, threads_for(n, 8192, nthreads), [&](int64_t c, int) {
        int64_t *cnt = cursors + c * ntiles;
        const int64_t r1 = std::min(n, (c + 1) * ((n + nch - 1) / nch));
        for (int64_t r = c * ((n + nch - 1) / nch); r < r1; ++r) {
            if (r + 8 < r1) __builtin_prefetch(splats + order[r + 8]);
            for_each_tile(splats[order[r]], TS, ntx, [&](int64_t t) { cnt[t]++; });
        }
    });
    int64_t total = 0;
    for (int64_t t = 0; t < ntiles; ++t) {
        tile_offsets[t] = total;
        for (int c = 0; c < nch; ++c) {
            const int64_t k = cursors[c * ntiles + t];
            cursors[c * ntiles + t] = total;
            total += k;
        }
    }
    tile_offsets[ntiles] = total;
    return total;
}

template <typename T>
int fill_impl(int64_t M, int W, int H, int TS, int nthreads, const Splat<T> *splats, const int32_t *order,
              int nch, const int64_t *cursors, int32_t *isect) {
    const int ntx = (W + TS - 1) / TS, nty = (H + TS - 1) / TS;
    const int64_t ntiles = (int64_t)ntx * nty;
    int64_t n = 0;
    while (n < M && order[n] >= 0) ++n;
    parallel_for(nch, threads_for(n, 8192, nthreads), [&](int64_t c, int) {
        std::vector<int64_t> cur(cursors + c * ntiles, cursors + (c + 1) * ntiles);
        const int64_t r1 = std::min(n, (c + 1) * ((n + nch - 1) / nch));
        for (int64_t r = c * ((n + nch - 1) / nch); r < r1; ++r) {
            const int32_t g = order[r];
            if (r + 8 < r1) __builtin_prefetch(splats + order[r + 8]);
            for_each_tile(splats[g], TS, ntx, [&](int64_t t) { isect[cur[(size_t)t]++] = g; });
        }
    });
    return 0;
}

// ----------------------------------------------------------------------------
// Channel NC - 1 (the `depth` array) is the camera depth: the outputs are the features
// (H, W, NC - 1) with the background composited, alpha (H, W) and the expected
// depth (H, W) = sum(w z) / max(alpha, 1e-10); T, the depth sum and the last
// composited index per pixel are kept for the backward pass.
template <typename T>
struct FwdArgs {
    int64_t M;
    int NC, W, H, TS;
    const Splat<T> *splats;
    const T *features, *depth;  // (M, NC - 1) and (M,): the NC composited channels
    const T *bg;                // (NC - 1) background, or null
    const int64_t *tile_offsets;
    const int32_t *isect;
    T *out_feat, *out_alpha, *out_depth, *out_T, *out_accD;
    int32_t *out_last;
};

// Tile arrays are padded by one vector so that a vector starting at any pixel of
// the tile stays inside the allocation (lanes past the span are masked).
template <typename T>
struct FwdScratch {
    typedef typename VT<T>::IT IT;
    std::vector<T> Tr, alive, acc, fbuf;
    std::vector<IT> last;
    int stride;  // per-channel stride of acc
    void init(int TS, int NC) {
        fbuf.resize((size_t)NC);
        stride = TS * TS + VT<T>::V;
        Tr.resize((size_t)stride);
        alive.resize((size_t)stride);
        last.resize((size_t)stride);
        acc.resize((size_t)stride * NC);
    }
};

template <typename T, int NCT>
MOGAF_INLINE void forward_tile_body(const FwdArgs<T> &A, int64_t t, FwdScratch<T> &S) {
    typedef typename VT<T>::vT vT;
    typedef typename VT<T>::vM vM;
    typedef typename VT<T>::IT IT;
    constexpr int V = VT<T>::V;
    const int NC = NCT > 0 ? NCT : A.NC;
    const int TS = A.TS, W = A.W, H = A.H;
    const int ST = S.stride;
    const int ntx = (W + TS - 1) / TS;
    const int tx = (int)(t % ntx), ty = (int)(t / ntx);
    const int px0 = tx * TS, py0 = ty * TS;
    const int tw = std::min(TS, W - px0), th = std::min(TS, H - py0);
    T *__restrict Tr = S.Tr.data();
    T *__restrict alive = S.alive.data();
    T *__restrict acc = S.acc.data();
    IT *__restrict last = S.last.data();
    for (int p = 0; p < ST; ++p) {
        Tr[p] = (T)1;
        alive[p] = (T)1;
        last[p] = -1;
    }
    std::fill(S.acc.begin(), S.acc.end(), (T)0);
    const vT vzero = vT{}, vone = vT{} + (T)1, vhalf = vT{} + (T)0.5;
    const vT vamin = vT{} + (T)kAlphaMin, vamax = vT{} + (T)kAlphaMax, vtmin = vT{} + (T)kTMin;
    const vT lanef = lane_index<vT, V>();
    const vM lanei = lane_index<vM, V>();
    int rowalive[kMaxTile];
    for (int jj = 0; jj < th; ++jj) rowalive[jj] = tw;
    const int npix = tw * th;
    int ndone = 0;
    vM nstop = vM{};
    const int64_t k0 = A.tile_offsets[t], k1 = A.tile_offsets[t + 1];
    T fc[NCT > 0 ? NCT : 1];
    T *f = NCT > 0 ? fc : S.fbuf.data();
    for (int64_t k = k0; k < k1 && ndone < npix; ++k) {
        const int32_t g = A.isect[k];
        if (k + 2 < k1) {
            __builtin_prefetch(A.splats + A.isect[k + 2]);
            __builtin_prefetch(A.features + (size_t)A.isect[k + 2] * (NC - 1));
        }
        const vM vk = vM{} + (IT)k;
        const Splat<T> s = A.splats[g];
        for (int c = 0; c < NC - 1; ++c) f[c] = A.features[(size_t)g * (NC - 1) + c];
        f[NC - 1] = A.depth[g];
        const int jlo = std::max(s.j0, py0), jhi = std::min(s.j1, py0 + th - 1);
        for (int j = jlo; j <= jhi; ++j) {
            const int jj = j - py0;
            if (rowalive[jj] == 0) continue;
            int ia, ib;
            if (!row_span(s, j, ia, ib)) continue;
            ia = std::max(ia, px0);
            ib = std::min(ib, px0 + tw - 1);
            const T dy = s.my - ((T)j + (T)0.5);
            const T cdy = s.c * dy * dy;
            const T bdy = s.b * dy;
            const int rowbase = jj * TS - px0;
            for (int i = ia; i <= ib; i += V) {
                const int p = rowbase + i;
                const vM valid = (lanei + i) <= ib;
                const vT dx = s.mx - (((T)i + lanef) + vhalf);
                const vT sigma = vhalf * (s.a * dx * dx + cdy) + bdy * dx;
                const vT G = vexp(-sigma);
                vT alpha = s.o * G;
                alpha = vsel<vT, vM>(alpha < vamax, alpha, vamax);
                const vT Tp = vload<vT>(Tr + p);
                const vT al = vload<vT>(alive + p);
                const vM la = vload<vM>(last + p);
                const vT nT = Tp * (vone - alpha);
                const vM act = valid & (alpha >= vamin) & (al != vzero);
                const vM stop = act & (nT <= vtmin);
                const vM con = act & (nT > vtmin);
                const vT wgt = vsel<vT, vM>(con, alpha * Tp, vzero);
                vstore(Tr + p, vsel<vT, vM>(con, nT, Tp));
                vstore(alive + p, vsel<vT, vM>(stop, vzero, al));
                vstore(last + p, isel<vM>(con, vk, la));
                nstop -= stop;
                if (NCT > 0) {
                    for (int c = 0; c < NCT; ++c) {
                        T *ap = acc + (size_t)c * ST + p;
                        vstore(ap, vload<vT>(ap) + wgt * f[c]);
                    }
                } else {
                    for (int c = 0; c < NC; ++c) {
                        T *ap = acc + (size_t)c * ST + p;
                        vstore(ap, vload<vT>(ap) + wgt * f[c]);
                    }
                }
            }
        }
        // Pixels stop at most once per tile: recount the rows only when some did.
        int ns = 0;
        for (int l = 0; l < V; ++l) ns += (int)nstop[l];
        if (ns > 0) {
            ndone += ns;
            nstop = vM{};
            for (int j = jlo; j <= jhi; ++j) {
                const int jj = j - py0;
                int n = 0;
                for (int ii = 0; ii < tw; ++ii) n += alive[jj * TS + ii] != (T)0;
                rowalive[jj] = n;
            }
        }
    }
    for (int jj = 0; jj < th; ++jj)
        for (int ii = 0; ii < tw; ++ii) {
            const int p = jj * TS + ii;
            const size_t q = (size_t)(py0 + jj) * W + (px0 + ii);
            const T Tq = Tr[p], Aq = (T)1 - Tr[p];
            const int C = NC - 1;
            A.out_T[q] = Tq;
            A.out_last[q] = (int32_t)last[p];
            for (int c = 0; c < C; ++c)
                A.out_feat[q * C + c] = acc[(size_t)c * ST + p] + (A.bg != nullptr ? Tq * A.bg[c] : (T)0);
            const T accD = acc[(size_t)C * ST + p];
            A.out_accD[q] = accD;
            A.out_alpha[q] = Aq;
            A.out_depth[q] = accD / (Aq > (T)1e-10 ? Aq : (T)1e-10);
        }
}

// ----------------------------------------------------------------------------
template <typename T>
struct BwdArgs {
    int64_t M;
    int NC, W, H, TS;
    const Splat<T> *splats;
    const T *features, *depth;
    const T *bg;
    const int64_t *tile_offsets;
    const int32_t *isect;
    const T *out_T, *out_accD;
    const int32_t *out_last;
    const T *g_feat, *g_alpha, *g_depth;
    T *pair;
};

template <typename T>
struct BwdScratch {
    typedef typename VT<T>::IT IT;
    typedef typename VT<T>::vT vT;
    std::vector<T> Tr, gS, gATf, gC;
    std::vector<IT> last;
    std::vector<T> accf;  // NC x V feature-gradient accumulators (generic channel count)
    std::vector<T> fbuf;
    int stride;
    void init(int TS, int NC) {
        fbuf.resize((size_t)NC);
        stride = TS * TS + VT<T>::V;
        Tr.resize((size_t)stride);
        gS.resize((size_t)stride);
        gATf.resize((size_t)stride);
        last.resize((size_t)stride);
        gC.resize((size_t)stride * NC);
        accf.resize((size_t)NC * VT<T>::V);
    }
};

template <typename T, int NCT>
MOGAF_INLINE void backward_tile_body(const BwdArgs<T> &A, int64_t t, BwdScratch<T> &S) {
    typedef typename VT<T>::vT vT;
    typedef typename VT<T>::vM vM;
    typedef typename VT<T>::IT IT;
    constexpr int V = VT<T>::V;
    const int NC = NCT > 0 ? NCT : A.NC;
    const int PS = 6 + NC;  // per-pair record: mx, my, a, b, c, o, features
    const int TS = A.TS, W = A.W, H = A.H;
    const int ST = S.stride;
    const int ntx = (W + TS - 1) / TS;
    const int tx = (int)(t % ntx), ty = (int)(t / ntx);
    const int px0 = tx * TS, py0 = ty * TS;
    const int tw = std::min(TS, W - px0), th = std::min(TS, H - py0);
    T *__restrict Tr = S.Tr.data();
    T *__restrict gS = S.gS.data();
    T *__restrict gATf = S.gATf.data();
    T *__restrict gC = S.gC.data();
    IT *__restrict last = S.last.data();
    std::fill(S.Tr.begin(), S.Tr.end(), (T)1);
    std::fill(S.gS.begin(), S.gS.end(), (T)0);
    std::fill(S.gATf.begin(), S.gATf.end(), (T)0);
    std::fill(S.gC.begin(), S.gC.end(), (T)0);
    std::fill(S.last.begin(), S.last.end(), (IT)-1);
    const int64_t k0 = A.tile_offsets[t], k1 = A.tile_offsets[t + 1];
    int64_t kmax = k0 - 1;
    int64_t rowmax[kMaxTile];
    for (int jj = 0; jj < th; ++jj) {
        rowmax[jj] = -1;
        for (int ii = 0; ii < tw; ++ii) {
            const int p = jj * TS + ii;
            const size_t q = (size_t)(py0 + jj) * W + (px0 + ii);
            // Chain rule through feat = acc + T bg, alpha = 1 - T, depth = accD / max(alpha, 1e-10).
            const T Tq = A.out_T[q], Aq = (T)1 - Tq;
            const int C = NC - 1;
            const T gd = A.g_depth != nullptr ? A.g_depth[q] : (T)0;
            T gA = A.g_alpha != nullptr ? A.g_alpha[q] : (T)0;
            if (Aq > (T)1e-10) gA -= gd * A.out_accD[q] / (Aq * Aq);
            for (int c = 0; c < C; ++c) {
                const T gf = A.g_feat != nullptr ? A.g_feat[q * C + c] : (T)0;
                gC[(size_t)c * ST + p] = gf;
                if (A.bg != nullptr) gA -= gf * A.bg[c];
            }
            gC[(size_t)C * ST + p] = gd / (Aq > (T)1e-10 ? Aq : (T)1e-10);
            Tr[p] = Tq;
            gATf[p] = gA * Tq;
            last[p] = A.out_last[q];
            rowmax[jj] = std::max<int64_t>(rowmax[jj], A.out_last[q]);
        }
        kmax = std::max<int64_t>(kmax, rowmax[jj]);
    }
    for (int64_t k = std::max(kmax + 1, k0); k < k1; ++k) std::memset(A.pair + (size_t)k * PS, 0, sizeof(T) * PS);
    const vT vzero = vT{}, vone = vT{} + (T)1, vhalf = vT{} + (T)0.5;
    const vT vamin = vT{} + (T)kAlphaMin, vamax = vT{} + (T)kAlphaMax;
    const vT lanef = lane_index<vT, V>();
    const vM lanei = lane_index<vM, V>();
    T fc[NCT > 0 ? NCT : 1];
    T *f = NCT > 0 ? fc : S.fbuf.data();
    vT accf[NCT > 0 ? NCT : 1];  // fixed channel count: in registers
    T *accd = S.accf.data();     // generic channel count: unaligned memory
    for (int64_t k = kmax; k >= k0; --k) {
        const int32_t g = A.isect[k];
        if (k - 2 >= k0) {
            __builtin_prefetch(A.splats + A.isect[k - 2]);
            __builtin_prefetch(A.features + (size_t)A.isect[k - 2] * (NC - 1));
        }
        const vM vk = vM{} + (IT)k;
        const Splat<T> s = A.splats[g];
        for (int c = 0; c < NC - 1; ++c) f[c] = A.features[(size_t)g * (NC - 1) + c];
        f[NC - 1] = A.depth[g];
        vT amx = vzero, amy = vzero, aa = vzero, ab = vzero, ac = vzero, ao = vzero;
        if (NCT > 0) {
            for (int c = 0; c < NCT; ++c) accf[c] = vzero;
        } else {
            std::fill(S.accf.begin(), S.accf.end(), (T)0);
        }
        const int jlo = std::max(s.j0, py0), jhi = std::min(s.j1, py0 + th - 1);
        for (int j = jlo; j <= jhi; ++j) {
            const int jj = j - py0;
            if (rowmax[jj] < k) continue;
            int ia, ib;
            if (!row_span(s, j, ia, ib)) continue;
            ia = std::max(ia, px0);
            ib = std::min(ib, px0 + tw - 1);
            const T dy = s.my - ((T)j + (T)0.5);
            const T cdy = s.c * dy * dy;
            const T bdy = s.b * dy;
            const T hdy2 = (T)0.5 * dy * dy;
            const int rowbase = jj * TS - px0;
            for (int i = ia; i <= ib; i += V) {
                const int p = rowbase + i;
                const vM valid = (lanei + i) <= ib;
                const vT dx = s.mx - (((T)i + lanef) + vhalf);
                const vT sigma = vhalf * (s.a * dx * dx + cdy) + bdy * dx;
                const vT G = vexp(-sigma);
                const vT raw = s.o * G;
                const vT alpha = vsel<vT, vM>(raw < vamax, raw, vamax);
                const vM la = vload<vM>(last + p);
                const vM act = valid & (la >= vk) & (alpha >= vamin);
                const vT inv_om = vone / (vone - alpha);
                const vT Tp = vload<vT>(Tr + p);
                const vT gSp = vload<vT>(gS + p);
                const vT Ti = Tp * inv_om;
                const vT wgt = alpha * Ti;
                vT dot = vzero;
                if (NCT > 0) {
                    for (int c = 0; c < NCT; ++c) dot += f[c] * vload<vT>(gC + (size_t)c * ST + p);
                } else {
                    for (int c = 0; c < NC; ++c) dot += f[c] * vload<vT>(gC + (size_t)c * ST + p);
                }
                const vT dLda = Ti * dot - (gSp - vload<vT>(gATf + p)) * inv_om;
                vstore(gS + p, vsel<vT, vM>(act, gSp + wgt * dot, gSp));
                vstore(Tr + p, vsel<vT, vM>(act, Ti, Tp));
                const vT wa = vsel<vT, vM>(act, wgt, vzero);
                const vT dl = vsel<vT, vM>(act & (raw < vamax), dLda, vzero);
                const vT dLds = -alpha * dl;
                ao += G * dl;
                amx += (s.a * dx + bdy) * dLds;
                amy += (s.b * dx + s.c * dy) * dLds;
                aa += vhalf * dx * dx * dLds;
                ab += dx * dy * dLds;
                ac += hdy2 * dLds;
                if (NCT > 0) {
                    for (int c = 0; c < NCT; ++c) accf[c] += wa * vload<vT>(gC + (size_t)c * ST + p);
                } else {
                    for (int c = 0; c < NC; ++c)
                        vstore(accd + c * V, vload<vT>(accd + c * V) + wa * vload<vT>(gC + (size_t)c * ST + p));
                }
            }
        }
        T *pr = A.pair + (size_t)k * PS;
        T r[6] = {0, 0, 0, 0, 0, 0};
        for (int l = 0; l < V; ++l) {
            r[0] += amx[l];
            r[1] += amy[l];
            r[2] += aa[l];
            r[3] += ab[l];
            r[4] += ac[l];
            r[5] += ao[l];
        }
        for (int q = 0; q < 6; ++q) pr[q] = r[q];
        for (int c = 0; c < NC; ++c) {
            T sum = 0;
            for (int l = 0; l < V; ++l) sum += NCT > 0 ? accf[NCT > 0 ? c : 0][l] : accd[c * V + l];
            pr[6 + c] = sum;
        }
    }
}
// One clone-able tile function per (type, channel count): the bodies are inlined
// into each clone, so the AVX2 clone is compiled with AVX2; the per-tile call
// goes through the ifunc resolved at load time.
#define MOGAF_TILE_FNS_ATTR(T, SUF, NCT, ATTR)                                                                   \
    ATTR void fwd_tile_##SUF##_##NCT(const FwdArgs<T> &A, int64_t t, FwdScratch<T> &S) {                         \
        forward_tile_body<T, NCT>(A, t, S);                                                                      \
    }                                                                                                            \
    ATTR void bwd_tile_##SUF##_##NCT(const BwdArgs<T> &A, int64_t t, BwdScratch<T> &S) {                         \
        backward_tile_body<T, NCT>(A, t, S);                                                                     \
    }                                                                                                            \
    void fwd_tiles_##SUF##_##NCT(const FwdArgs<T> &A, int nthreads) {                                            \
        const int ntx = (A.W + A.TS - 1) / A.TS, nty = (A.H + A.TS - 1) / A.TS;                                  \
        const int64_t ntiles = (int64_t)ntx * nty;                                                               \
        const int nw = threads_for(A.tile_offsets[ntiles], 4096, (int)std::min<int64_t>(nthreads, ntiles));      \
        std::vector<FwdScratch<T>> S((size_t)nw);                                                                \
        for (auto &s : S) s.init(A.TS, A.NC);                                                                    \
        const std::vector<int64_t> ids = tiles_by_cost(A.tile_offsets, ntiles);                                  \
        parallel_for(ntiles, nw, [&](int64_t i, int w) { fwd_tile_##SUF##_##NCT(A, ids[(size_t)i], S[(size_t)w]); }); \
    }                                                                                                            \
    void bwd_tiles_##SUF##_##NCT(const BwdArgs<T> &A, int nthreads) {                                            \
        const int ntx = (A.W + A.TS - 1) / A.TS, nty = (A.H + A.TS - 1) / A.TS;                                  \
        const int64_t ntiles = (int64_t)ntx * nty;                                                               \
        const int nw = threads_for(A.tile_offsets[ntiles], 4096, (int)std::min<int64_t>(nthreads, ntiles));      \
        std::vector<BwdScratch<T>> S((size_t)nw);                                                                \
        for (auto &s : S) s.init(A.TS, A.NC);                                                                    \
        const std::vector<int64_t> ids = tiles_by_cost(A.tile_offsets, ntiles);                                  \
        parallel_for(ntiles, nw, [&](int64_t i, int w) { bwd_tile_##SUF##_##NCT(A, ids[(size_t)i], S[(size_t)w]); }); \
    }

#define MOGAF_TILE_FNS(T, SUF, NCT) MOGAF_TILE_FNS_ATTR(T, SUF, NCT, MOGAF_CLONES)
#define MOGAF_NOCLONE
// float64 is for tests and gradient checks: one generic, unclone build is enough.
MOGAF_TILE_FNS_ATTR(double, f64, 0, MOGAF_NOCLONE)
MOGAF_TILE_FNS(float, f32, 0)
MOGAF_TILE_FNS(float, f32, 1)
MOGAF_TILE_FNS(float, f32, 2)
MOGAF_TILE_FNS(float, f32, 3)
MOGAF_TILE_FNS(float, f32, 4)
MOGAF_TILE_FNS(float, f32, 5)
MOGAF_TILE_FNS(float, f32, 6)
MOGAF_TILE_FNS(float, f32, 7)
MOGAF_TILE_FNS(float, f32, 8)

void fwd_tiles(const FwdArgs<float> &A, int nt) {
    switch (A.NC) {
        case 1: fwd_tiles_f32_1(A, nt); break;
        case 2: fwd_tiles_f32_2(A, nt); break;
        case 3: fwd_tiles_f32_3(A, nt); break;
        case 4: fwd_tiles_f32_4(A, nt); break;
        case 5: fwd_tiles_f32_5(A, nt); break;
        case 6: fwd_tiles_f32_6(A, nt); break;
        case 7: fwd_tiles_f32_7(A, nt); break;
        case 8: fwd_tiles_f32_8(A, nt); break;
        default: fwd_tiles_f32_0(A, nt); break;
    }
}
void fwd_tiles(const FwdArgs<double> &A, int nt) { fwd_tiles_f64_0(A, nt); }
void bwd_tiles(const BwdArgs<float> &A, int nt) {
    switch (A.NC) {
        case 1: bwd_tiles_f32_1(A, nt); break;
        case 2: bwd_tiles_f32_2(A, nt); break;
        case 3: bwd_tiles_f32_3(A, nt); break;
        case 4: bwd_tiles_f32_4(A, nt); break;
        case 5: bwd_tiles_f32_5(A, nt); break;
        case 6: bwd_tiles_f32_6(A, nt); break;
        case 7: bwd_tiles_f32_7(A, nt); break;
        case 8: bwd_tiles_f32_8(A, nt); break;
        default: bwd_tiles_f32_0(A, nt); break;
    }
}
void bwd_tiles(const BwdArgs<double> &A, int nt) { bwd_tiles_f64_0(A, nt); }

template <typename T>
int forward_impl(int64_t M, int NC, int W, int H, int TS, int nthreads, const void *splats, const T *features,
                 const T *depth, const T *bg, const int64_t *tile_offsets, const int32_t *isect, T *out_feat, T *out_alpha,
                 T *out_depth, T *out_T, T *out_accD, int32_t *out_last) {
    if (TS < 1 || TS > kMaxTile || NC < 1) return -3;
    FwdArgs<T> A{M,        NC,        W,         H,     TS,       (const Splat<T> *)splats, features, depth, bg,
                 tile_offsets, isect,    out_feat,  out_alpha, out_depth, out_T, out_accD, out_last};
    fwd_tiles(A, nthreads);
    return 0;
}

template <typename T>
int backward_impl(int64_t M, int NC, int W, int H, int TS, int nthreads, const void *splats, const T *features,
                  const T *depth, const T *bg, const int64_t *tile_offsets, const int32_t *isect, const T *out_T, const T *out_accD,
                  const int32_t *out_last, const T *g_feat, const T *g_alpha, const T *g_depth, T *pair,
                  T *g_means2d, T *g_conics, T *g_opac, T *g_features, T *g_depthv) {
    if (TS < 1 || TS > kMaxTile || NC < 1) return -3;
    BwdArgs<T> A{M,     NC,       W,        H,      TS,      (const Splat<T> *)splats, features, depth, bg,
                 tile_offsets, isect, out_T,    out_accD, out_last, g_feat, g_alpha,                 g_depth, pair};
    bwd_tiles(A, nthreads);
    // Deterministic reduction of the per-(tile, Gaussian) records.
    const int PS = 6 + NC;
    std::memset(g_means2d, 0, sizeof(T) * 2 * (size_t)M);
    std::memset(g_conics, 0, sizeof(T) * 3 * (size_t)M);
    std::memset(g_opac, 0, sizeof(T) * (size_t)M);
    std::memset(g_features, 0, sizeof(T) * (NC - 1) * (size_t)M);
    std::memset(g_depthv, 0, sizeof(T) * (size_t)M);
    const int ntx = (W + TS - 1) / TS, nty = (H + TS - 1) / TS;
    const int64_t n_isect = tile_offsets[(int64_t)ntx * nty];
    for (int64_t k = 0; k < n_isect; ++k) {
        const size_t g = (size_t)isect[k];
        const T *pr = pair + (size_t)k * PS;
        g_means2d[2 * g] += pr[0];
        g_means2d[2 * g + 1] += pr[1];
        g_conics[3 * g] += pr[2];
        g_conics[3 * g + 1] += pr[3];
        g_conics[3 * g + 2] += pr[4];
        g_opac[g] += pr[5];
        T *gfp = g_features + g * (NC - 1);
        for (int c = 0; c < NC - 1; ++c) gfp[c] += pr[6 + c];
        g_depthv[g] += pr[5 + NC];
    }
    return 0;
}

// ----------------------------------------------------------------------------
// Fused EWA projection (forward and analytic backward), the same mathematics as
// mogaf/render/projection.py (which is the pure-torch version), evaluated in
// double precision per Gaussian.
struct Camera {
    double R[9], t[3];  // world-to-camera rotation (row-major) and translation
    double fx, fy, cx, cy;
    int W, H;
    double near_plane, far_plane, eps2d;
    double lxp, lxn, lyp, lyn;  // clamp limits of x/z, y/z (1.3x the field of view)
};

inline Camera make_camera(const double *cam, int W, int H, double near_plane, double far_plane, double eps2d) {
    // cam: viewmat (16, row-major) then fx, fy, cx, cy
    Camera c;
    for (int r = 0; r < 3; ++r) {
        for (int k = 0; k < 3; ++k) c.R[3 * r + k] = cam[4 * r + k];
        c.t[r] = cam[4 * r + 3];
    }
    c.fx = cam[16];
    c.fy = cam[17];
    c.cx = cam[18];
    c.cy = cam[19];
    c.W = W;
    c.H = H;
    c.near_plane = near_plane;
    c.far_plane = far_plane;
    c.eps2d = eps2d;
    const double tfx = 0.5 * W / c.fx, tfy = 0.5 * H / c.fy;
    c.lxp = (W - c.cx) / c.fx + 0.3 * tfx;
    c.lxn = c.cx / c.fx + 0.3 * tfx;
    c.lyp = (H - c.cy) / c.fy + 0.3 * tfy;
    c.lyn = c.cy / c.fy + 0.3 * tfy;
    return c;
}

struct ProjFwd {
    // inputs (double copies)
    double p[3], q[4], s[3];
    // intermediates
    bool q_ok;
    double qn[4], qnorm, Rq[9], M[9], A[9], pc[3];
    bool in_range;
    double zs, rz, ux, uy, cux, cuy, tx, ty, u[3], v[3], uu, vv, uv, sxx, syy, sxy, cr[3], det;
    double mx, my;
};

template <typename T>
MOGAF_INLINE void proj_forward(const Camera &C, const T *means, const T *quats, const T *scales, int64_t g,
                               ProjFwd &F) {
    for (int k = 0; k < 3; ++k) {
        F.p[k] = (double)means[3 * g + k];
        F.s[k] = (double)scales[3 * g + k];
    }
    for (int k = 0; k < 4; ++k) F.q[k] = (double)quats[4 * g + k];
    const double n2 = F.q[0] * F.q[0] + F.q[1] * F.q[1] + F.q[2] * F.q[2] + F.q[3] * F.q[3];
    F.q_ok = n2 > 1e-24;
    F.qnorm = F.q_ok ? std::sqrt(n2) : 1.0;
    for (int k = 0; k < 4; ++k) F.qn[k] = F.q_ok ? F.q[k] / F.qnorm : (k == 0 ? 1.0 : 0.0);
    const double w = F.qn[0], x = F.qn[1], y = F.qn[2], z = F.qn[3];
    double *R = F.Rq;
    R[0] = 1 - 2 * (y * y + z * z);
    R[1] = 2 * (x * y - w * z);
    R[2] = 2 * (x * z + w * y);
    R[3] = 2 * (x * y + w * z);
    R[4] = 1 - 2 * (x * x + z * z);
    R[5] = 2 * (y * z - w * x);
    R[6] = 2 * (x * z - w * y);
    R[7] = 2 * (y * z + w * x);
    R[8] = 1 - 2 * (x * x + y * y);
    for (int r = 0; r < 3; ++r)
        for (int k = 0; k < 3; ++k) F.M[3 * r + k] = R[3 * r + k] * F.s[k];
    for (int r = 0; r < 3; ++r) {
        F.pc[r] = C.t[r];
        for (int k = 0; k < 3; ++k) F.pc[r] += C.R[3 * r + k] * F.p[k];
        for (int k = 0; k < 3; ++k) {
            double a = 0;
            for (int m = 0; m < 3; ++m) a += C.R[3 * r + m] * F.M[3 * m + k];
            F.A[3 * r + k] = a;
        }
    }
    const double zc = F.pc[2];
    F.in_range = zc >= C.near_plane && zc <= C.far_plane;
    F.zs = F.in_range ? zc : 1.0;
    F.rz = 1.0 / F.zs;
    F.ux = F.pc[0] * F.rz;
    F.uy = F.pc[1] * F.rz;
    F.cux = std::min(std::max(F.ux, -C.lxn), C.lxp);
    F.cuy = std::min(std::max(F.uy, -C.lyn), C.lyp);
    F.tx = F.zs * F.cux;
    F.ty = F.zs * F.cuy;
    const double al = C.fx * F.rz, be = C.fx * F.tx * F.rz * F.rz;
    const double ga = C.fy * F.rz, de = C.fy * F.ty * F.rz * F.rz;
    for (int k = 0; k < 3; ++k) {
        F.u[k] = al * F.A[k] - be * F.A[6 + k];
        F.v[k] = ga * F.A[3 + k] - de * F.A[6 + k];
    }
    F.uu = F.u[0] * F.u[0] + F.u[1] * F.u[1] + F.u[2] * F.u[2];
    F.vv = F.v[0] * F.v[0] + F.v[1] * F.v[1] + F.v[2] * F.v[2];
    F.uv = F.u[0] * F.v[0] + F.u[1] * F.v[1] + F.u[2] * F.v[2];
    F.sxx = F.uu + C.eps2d;
    F.syy = F.vv + C.eps2d;
    F.sxy = F.uv;
    F.cr[0] = F.u[1] * F.v[2] - F.u[2] * F.v[1];
    F.cr[1] = F.u[2] * F.v[0] - F.u[0] * F.v[2];
    F.cr[2] = F.u[0] * F.v[1] - F.u[1] * F.v[0];
    F.det = F.cr[0] * F.cr[0] + F.cr[1] * F.cr[1] + F.cr[2] * F.cr[2] + C.eps2d * (F.uu + F.vv) + C.eps2d * C.eps2d;
    F.mx = C.fx * F.pc[0] * F.rz + C.cx;
    F.my = C.fy * F.pc[1] * F.rz + C.cy;
}

template <typename T>
void project_impl(int64_t N, const T *means, const T *quats, const T *scales, const T *opac, const Camera &C,
                  int nthreads, T *means2d, T *conics, T *depths, int32_t *radii, uint8_t *visible) {
    const int64_t chunk = 1024;
    parallel_for((N + chunk - 1) / chunk, threads_for(N, 8192, nthreads), [&](int64_t ci, int) {
        const int64_t g1 = std::min(N, (ci + 1) * chunk);
        for (int64_t g = ci * chunk; g < g1; ++g) {
            ProjFwd F;
            proj_forward(C, means, quats, scales, g, F);
            depths[g] = (T)F.pc[2];
            const double o = (double)opac[g];
            double ext = 0.0;
            if (o >= kAlphaMin) ext = std::min(3.33, std::sqrt(2.0 * std::log(std::max(o / kAlphaMin, 1.0))));
            double rx = std::ceil(ext * std::sqrt(F.sxx)), ry = std::ceil(ext * std::sqrt(F.syy));
            const bool finite = std::isfinite(F.mx) && std::isfinite(F.my) && std::isfinite(F.sxx) &&
                                std::isfinite(F.syy) && std::isfinite(F.sxy) && std::isfinite(F.det) && F.det > 0.0;
            if (!finite || !(rx >= 0.0)) rx = 0.0;
            if (!finite || !(ry >= 0.0)) ry = 0.0;
            rx = std::min(rx, 1073741824.0);
            ry = std::min(ry, 1073741824.0);
            const bool onscreen = (F.mx + rx > 0) && (F.mx - rx < C.W) && (F.my + ry > 0) && (F.my - ry < C.H);
            const bool vis = F.in_range && finite && (rx > 0 || ry > 0) && onscreen;
            if (visible != nullptr) visible[g] = vis ? 1 : 0;
            radii[2 * g] = vis ? (int32_t)rx : 0;
            radii[2 * g + 1] = vis ? (int32_t)ry : 0;
            means2d[2 * g] = vis ? (T)F.mx : (T)0;
            means2d[2 * g + 1] = vis ? (T)F.my : (T)0;
            conics[3 * g] = vis ? (T)(F.syy / F.det) : (T)0;
            conics[3 * g + 1] = vis ? (T)(-F.sxy / F.det) : (T)0;
            conics[3 * g + 2] = vis ? (T)(F.sxx / F.det) : (T)0;
        }
    });
}

template <typename T>
void project_backward_impl(int64_t N, const T *means, const T *quats, const T *scales, const Camera &C,
                           int nthreads, const int32_t *radii, const T *v_means2d, const T *v_conics,
                           const T *v_depths, T *g_means, T *g_quats, T *g_scales, double *g_view) {
    const int64_t chunk = 1024;
    const int64_t nchunks = (N + chunk - 1) / chunk;
    std::vector<double> part((size_t)std::max<int64_t>(nchunks, 1) * 12, 0.0);  // per chunk: dR (9), dt (3)
    parallel_for(nchunks, threads_for(N, 4096, nthreads), [&](int64_t ci, int) {
        double *pv = part.data() + ci * 12;
        const int64_t g1 = std::min(N, (ci + 1) * chunk);
        for (int64_t g = ci * chunk; g < g1; ++g) {
            ProjFwd F;
            proj_forward(C, means, quats, scales, g, F);
            const bool vis = radii[2 * g] > 0 || radii[2 * g + 1] > 0;
            double gpc[3] = {0, 0, v_depths != nullptr ? (double)v_depths[g] : 0.0};
            double gA[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
            if (vis && (v_means2d != nullptr || v_conics != nullptr)) {
                const double gmx = v_means2d ? (double)v_means2d[2 * g] : 0.0;
                const double gmy = v_means2d ? (double)v_means2d[2 * g + 1] : 0.0;
                const double ga = v_conics ? (double)v_conics[3 * g] : 0.0;
                const double gb = v_conics ? (double)v_conics[3 * g + 1] : 0.0;
                const double gc = v_conics ? (double)v_conics[3 * g + 2] : 0.0;
                const double id = 1.0 / F.det;
                const double g_sxx = gc * id, g_syy = ga * id, g_sxy = -gb * id;
                const double g_det = -(ga * F.syy - gb * F.sxy + gc * F.sxx) * id * id;
                double gu[3], gv[3];
                const double cu = 2.0 * (g_sxx + C.eps2d * g_det), cv = 2.0 * (g_syy + C.eps2d * g_det);
                const double gcr[3] = {2.0 * g_det * F.cr[0], 2.0 * g_det * F.cr[1], 2.0 * g_det * F.cr[2]};
                // d(u x v): dL/du = v x gcr, dL/dv = gcr x u
                const double vxg[3] = {F.v[1] * gcr[2] - F.v[2] * gcr[1], F.v[2] * gcr[0] - F.v[0] * gcr[2],
                                       F.v[0] * gcr[1] - F.v[1] * gcr[0]};
                const double gxu[3] = {gcr[1] * F.u[2] - gcr[2] * F.u[1], gcr[2] * F.u[0] - gcr[0] * F.u[2],
                                       gcr[0] * F.u[1] - gcr[1] * F.u[0]};
                for (int k = 0; k < 3; ++k) {
                    gu[k] = cu * F.u[k] + g_sxy * F.v[k] + vxg[k];
                    gv[k] = cv * F.v[k] + g_sxy * F.u[k] + gxu[k];
                }
                const double rz = F.rz, rz2 = rz * rz;
                const double al = C.fx * rz, be = C.fx * F.tx * rz2, gam = C.fy * rz, de = C.fy * F.ty * rz2;
                double g_al = 0, g_be = 0, g_ga = 0, g_de = 0;
                for (int k = 0; k < 3; ++k) {
                    gA[k] += al * gu[k];
                    gA[3 + k] += gam * gv[k];
                    gA[6 + k] += -be * gu[k] - de * gv[k];
                    g_al += gu[k] * F.A[k];
                    g_be -= gu[k] * F.A[6 + k];
                    g_ga += gv[k] * F.A[3 + k];
                    g_de -= gv[k] * F.A[6 + k];
                }
                double g_rz = C.fx * g_al + C.fy * g_ga + 2.0 * C.fx * F.tx * rz * g_be + 2.0 * C.fy * F.ty * rz * g_de;
                const double g_tx = C.fx * rz2 * g_be, g_ty = C.fy * rz2 * g_de;
                double g_zs = 0.0;
                // tx = zs * clamp(ux); the clamp passes the gradient only inside the limits
                const bool fx_in = F.ux >= -C.lxn && F.ux <= C.lxp, fy_in = F.uy >= -C.lyn && F.uy <= C.lyp;
                g_zs += F.cux * g_tx + F.cuy * g_ty;
                const double g_ux = fx_in ? F.zs * g_tx : 0.0, g_uy = fy_in ? F.zs * g_ty : 0.0;
                gpc[0] += rz * g_ux;
                gpc[1] += rz * g_uy;
                g_rz += F.pc[0] * g_ux + F.pc[1] * g_uy;
                // mean2d
                gpc[0] += C.fx * rz * gmx;
                gpc[1] += C.fy * rz * gmy;
                g_rz += C.fx * F.pc[0] * gmx + C.fy * F.pc[1] * gmy;
                g_zs += -rz2 * g_rz;
                if (F.in_range) gpc[2] += g_zs;
            }
            // p_c = Rw p + t, A = Rw M
            double gp[3] = {0, 0, 0}, gM[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0};
            for (int r = 0; r < 3; ++r)
                for (int k = 0; k < 3; ++k) {
                    gp[k] += C.R[3 * r + k] * gpc[r];
                    for (int m = 0; m < 3; ++m) gM[3 * k + m] += C.R[3 * r + k] * gA[3 * r + m];
                }
            for (int r = 0; r < 3; ++r) {
                pv[9 + r] += gpc[r];
                for (int k = 0; k < 3; ++k) {
                    double acc = gpc[r] * F.p[k];
                    for (int m = 0; m < 3; ++m) acc += gA[3 * r + m] * F.M[3 * k + m];
                    pv[3 * r + k] += acc;
                }
            }
            // M = Rq diag(s)
            double gR[9];
            for (int r = 0; r < 3; ++r)
                for (int k = 0; k < 3; ++k) gR[3 * r + k] = gM[3 * r + k] * F.s[k];
            for (int k = 0; k < 3; ++k)
                g_scales[3 * g + k] = (T)(gM[k] * F.Rq[k] + gM[3 + k] * F.Rq[3 + k] + gM[6 + k] * F.Rq[6 + k]);
            for (int k = 0; k < 3; ++k) g_means[3 * g + k] = (T)gp[k];
            // rotation from the normalised quaternion, then the normalisation
            const double w = F.qn[0], x = F.qn[1], y = F.qn[2], z = F.qn[3];
            const double *G = gR;
            double gq[4];
            gq[0] = 2 * (-z * G[1] + y * G[2] + z * G[3] - x * G[5] - y * G[6] + x * G[7]);
            gq[1] = 2 * (y * G[1] + z * G[2] + y * G[3] - 2 * x * G[4] - w * G[5] + z * G[6] + w * G[7] - 2 * x * G[8]);
            gq[2] = 2 * (-2 * y * G[0] + x * G[1] + w * G[2] + x * G[3] + z * G[5] - w * G[6] + z * G[7] - 2 * y * G[8]);
            gq[3] = 2 * (-2 * z * G[0] - w * G[1] + x * G[2] + w * G[3] - 2 * z * G[4] + y * G[5] + x * G[6] + y * G[7]);
            if (F.q_ok) {
                const double dotq = gq[0] * w + gq[1] * x + gq[2] * y + gq[3] * z;
                for (int k = 0; k < 4; ++k) g_quats[4 * g + k] = (T)((gq[k] - F.qn[k] * dotq) / F.qnorm);
            } else {
                for (int k = 0; k < 4; ++k) g_quats[4 * g + k] = (T)0;
            }
        }
    });
    if (g_view != nullptr) {
        for (int k = 0; k < 16; ++k) g_view[k] = 0.0;
        for (int64_t ci = 0; ci < nchunks; ++ci) {
            const double *pv = part.data() + ci * 12;
            for (int r = 0; r < 3; ++r) {
                for (int k = 0; k < 3; ++k) g_view[4 * r + k] += pv[3 * r + k];
                g_view[4 * r + 3] += pv[9 + r];
            }
        }
    }
}

}  // namespace

// ---------------------------------------------------------------------------
// C ABI. Return values: >= 0 success (prepare: number of tile intersections),
// -1 out of memory, -2 other failure, -3 bad tile size. Arrays are C-contiguous.
//   prepare: splats (splat_bytes(M) bytes, out), order (M int32, out: visible
//            Gaussians front to back, then -1), tile_offsets (ntiles + 1 int64,
//            out), cursors (nch x ntiles int64 scratch, kept for fill)
//   fill:    isect (total int32, out): per tile, Gaussian ids front to back
//   forward: features (M, NC - 1) and depth (M) (the last channel, also the
//            sort key), bg (NC - 1, or null); out_feat (H, W, NC - 1), out_alpha, out_depth (H, W); kept
//            for backward: out_T (H, W) final transmittance, out_accD (H, W)
//            depth sum, out_last (H, W) index into isect of the last composited
//            Gaussian (-1: none)
//   backward: gradients of feat, alpha, depth in (each may be null: zero);
//            pair (total, 6 + NC) scratch; gradients for means2d (M, 2),
//            conics (M, 3), opacities (M), features (M, NC - 1), depth (M) out
extern "C" {

int mogaf_raster_abi_version() { return 6; }

#define MOGAF_GUARD(expr)              \
    try {                              \
        return (expr);                 \
    } catch (const std::bad_alloc &) { \
        return -1;                     \
    } catch (...) {                    \
        return -2;                     \
    }

#define MOGAF_DEFINE(SUF, T)                                                                                      \
    int64_t mogaf_splat_bytes_##SUF(int64_t M) { return M * (int64_t)sizeof(Splat<T>); }                          \
    int64_t mogaf_prepare_##SUF(int64_t M, int W, int H, int TS, int nthreads, const T *means2d,                   \
                                const T *conics, const T *opac, const int32_t *radii, const T *depths,            \
                                void *splats, int32_t *order, int64_t *tile_offsets, int nch, int64_t *cursors) { \
        if (TS < 1 || TS > kMaxTile || nch < 1) return -3;                                                        \
        MOGAF_GUARD(prepare_impl<T>(M, W, H, TS, nthreads, means2d, conics, opac, radii, depths,                  \
                                    (Splat<T> *)splats, order, tile_offsets, nch, cursors))                       \
    }                                                                                                             \
    int mogaf_fill_##SUF(int64_t M, int W, int H, int TS, int nthreads, const void *splats, const int32_t *order, \
                         int nch, const int64_t *cursors, int32_t *isect) {                                       \
        MOGAF_GUARD(fill_impl<T>(M, W, H, TS, nthreads, (const Splat<T> *)splats, order, nch, cursors, isect))    \
    }                                                                                                             \
    int mogaf_forward_##SUF(int64_t M, int NC, int W, int H, int TS, int nthreads, const void *splats,            \
                            const T *features, const T *depth, const T *bg, const int64_t *tile_offsets,          \
                            const int32_t *isect, T *out_feat, T *out_alpha, T *out_depth, T *out_T, T *out_accD, \
                            int32_t *out_last) {                                                                  \
        MOGAF_GUARD(forward_impl<T>(M, NC, W, H, TS, nthreads, splats, features, depth, bg, tile_offsets, isect,  \
                                    out_feat, out_alpha, out_depth, out_T, out_accD, out_last))                   \
    }                                                                                                             \
    int mogaf_backward_##SUF(int64_t M, int NC, int W, int H, int TS, int nthreads, const void *splats,           \
                             const T *features, const T *depth, const T *bg, const int64_t *tile_offsets,         \
                             const int32_t *isect, const T *out_T, const T *out_accD, const int32_t *out_last,    \
                             const T *g_feat, const T *g_alpha, const T *g_depth, T *pair, T *g_means2d,          \
                             T *g_conics, T *g_opac, T *g_features, T *g_depthv) {                                \
        MOGAF_GUARD(backward_impl<T>(M, NC, W, H, TS, nthreads, splats, features, depth, bg, tile_offsets, isect,  \
                                     out_T, out_accD, out_last, g_feat, g_alpha, g_depth, pair, g_means2d,        \
                                     g_conics, g_opac, g_features, g_depthv))                                     \
    }

#define MOGAF_DEFINE_PROJ(SUF, T)                                                                                 \
    int mogaf_project_##SUF(int64_t N, const T *means, const T *quats, const T *scales, const T *opac,            \
                            const double *cam, int W, int H, double near_plane, double far_plane, double eps2d,   \
                            int nthreads, T *means2d, T *conics, T *depths, int32_t *radii, uint8_t *visible) {   \
        MOGAF_GUARD((project_impl<T>(N, means, quats, scales, opac,                                               \
                                     make_camera(cam, W, H, near_plane, far_plane, eps2d), nthreads, means2d,     \
                                     conics, depths, radii, visible),                                             \
                     0))                                                                                          \
    }                                                                                                             \
    int mogaf_project_backward_##SUF(int64_t N, const T *means, const T *quats, const T *scales,                  \
                                     const double *cam, int W, int H, double near_plane, double far_plane,        \
                                     double eps2d, int nthreads, const int32_t *radii, const T *v_means2d,        \
                                     const T *v_conics, const T *v_depths, T *g_means, T *g_quats, T *g_scales,   \
                                     double *g_view) {                                                            \
        MOGAF_GUARD((project_backward_impl<T>(N, means, quats, scales,                                            \
                                              make_camera(cam, W, H, near_plane, far_plane, eps2d), nthreads,     \
                                              radii, v_means2d, v_conics, v_depths, g_means, g_quats, g_scales,   \
                                              g_view),                                                            \
                     0))                                                                                          \
    }

MOGAF_DEFINE(f32, float)
MOGAF_DEFINE(f64, double)
MOGAF_DEFINE_PROJ(f32, float)
MOGAF_DEFINE_PROJ(f64, double)

}  // extern "C"
