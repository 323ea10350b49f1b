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
                    radii[2 * g] >= 0 && radii[2 * g + 1] >= 0;
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

// Stable ascending order of depths (ties by index).
inline void depth_order(int64_t M, const float *depth, int32_t *order) {
    // LSD radix sort on order-preserving uint32 keys, 3 passes of 11 bits.
    std::vector<uint32_t> key((size_t)M), key2((size_t)M);
    std::vector<int32_t> tmp((size_t)M);
    for (int64_t i = 0; i < M; ++i) {
        uint32_t u;
        std::memcpy(&u, depth + i, 4);
        key[(size_t)i] = (u & 0x80000000u) ? ~u : (u | 0x80000000u);
        order[i] = (int32_t)i;
    }
    int32_t *src = order, *dst = tmp.data();
    uint32_t *ksrc = key.data(), *kdst = key2.data();
    for (int shift = 0; shift < 32; shift += 11) {
        std::vector<int64_t> cnt(2049, 0);
        for (int64_t i = 0; i < M; ++i) cnt[((ksrc[i] >> shift) & 2047u) + 1]++;
        for (int d = 0; d < 2048; ++d) cnt[d + 1] += cnt[d];
        for (int64_t i = 0; i < M; ++i) {
            const int64_t pos = cnt[(ksrc[i] >> shift) & 2047u]++;
            dst[pos] = src[i];
            kdst[pos] = ksrc[i];
        }
        std::swap(src, dst);
        std::swap(ksrc, kdst);
    }
    if (src != order) std::memcpy(order, src, sizeof(int32_t) * (size_t)M);
}

inline void depth_order(int64_t M, const double *depth, int32_t *order) {
    for (int64_t i = 0; i < M; ++i) order[i] = (int32_t)i;
    std::stable_sort(order, order + M, [&](int32_t x, int32_t y) { return depth[x] < depth[y]; });
}

template <typename T>
int64_t prepare_impl(int64_t M, int W, int H, int TS, int nthreads, const T *means2d, const T *conics,
                     const T *opac, const int32_t *radii, const T *depths, Splat<T> *splats, int32_t *order,
                     int64_t *tile_offsets) {
    const int ntx = (W + TS - 1) / TS, nty = (H + TS - 1) / TS;
    const int64_t ntiles = (int64_t)ntx * nty;
    const int64_t chunk = 4096;
    parallel_for((M + chunk - 1) / chunk, nthreads, [&](int64_t ci, int) {
        const int64_t g1 = std::min(M, (ci + 1) * chunk);
        for (int64_t g = ci * chunk; g < g1; ++g) splats[g] = make_splat(g, W, H, means2d, conics, opac, radii);
    });
    depth_order(M, depths, order);
    std::vector<int64_t> counts((size_t)ntiles, 0);
    for (int64_t g = 0; g < M; ++g) for_each_tile(splats[g], TS, ntx, [&](int64_t t) { counts[(size_t)t]++; });
    int64_t total = 0;
    for (int64_t t = 0; t < ntiles; ++t) {
        tile_offsets[t] = total;
        total += counts[(size_t)t];
    }
    tile_offsets[ntiles] = total;
    return total;
}

template <typename T>
int fill_impl(int64_t M, int W, int H, int TS, const Splat<T> *splats, const int32_t *order,
              const int64_t *tile_offsets, int32_t *isect) {
    const int ntx = (W + TS - 1) / TS, nty = (H + TS - 1) / TS;
    std::vector<int64_t> cursor(tile_offsets, tile_offsets + (int64_t)ntx * nty);
    for (int64_t r = 0; r < M; ++r) {
        const int32_t g = order[r];
        for_each_tile(splats[g], TS, ntx, [&](int64_t t) { isect[cursor[(size_t)t]++] = g; });
    }
    return 0;
}

// ----------------------------------------------------------------------------
template <typename T>
struct FwdArgs {
    int64_t M;
    int NC, W, H, TS;
    const Splat<T> *splats;
    const T *feats;
    const int64_t *tile_offsets;
    const int32_t *isect;
    T *out_acc, *out_T;
    int32_t *out_last;
};

// Tile arrays are padded by one vector so that a vector starting at any pixel of
// the tile stays inside the allocation (lanes past the span are masked).
template <typename T>
struct FwdScratch {
    typedef typename VT<T>::IT IT;
    std::vector<T> Tr, alive, acc;
    std::vector<IT> last;
    int stride;  // per-channel stride of acc
    void init(int TS, int NC) {
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
    for (int64_t k = k0; k < k1 && ndone < npix; ++k) {
        const int32_t g = A.isect[k];
        if (k + 2 < k1) {
            __builtin_prefetch(A.splats + A.isect[k + 2]);
            __builtin_prefetch(A.feats + (size_t)A.isect[k + 2] * NC);
        }
        const vM vk = vM{} + (IT)k;
        const Splat<T> s = A.splats[g];
        const T *f = A.feats + (size_t)g * NC;
        if (NCT > 0)
            for (int c = 0; c < NCT; ++c) fc[c] = f[c];
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
                        vstore(ap, vload<vT>(ap) + wgt * fc[c]);
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
            A.out_T[q] = Tr[p];
            A.out_last[q] = (int32_t)last[p];
            for (int c = 0; c < NC; ++c) A.out_acc[q * NC + c] = acc[(size_t)c * ST + p];
        }
}

// ----------------------------------------------------------------------------
template <typename T>
struct BwdArgs {
    int64_t M;
    int NC, W, H, TS;
    const Splat<T> *splats;
    const T *feats;
    const int64_t *tile_offsets;
    const int32_t *isect;
    const T *out_T;
    const int32_t *out_last;
    const T *g_acc, *g_alpha;
    T *pair;
};

template <typename T>
struct BwdScratch {
    typedef typename VT<T>::IT IT;
    typedef typename VT<T>::vT vT;
    std::vector<T> Tr, gS, gATf, gC;
    std::vector<IT> last;
    std::vector<vT> accf;
    int stride;
    void init(int TS, int NC) {
        stride = TS * TS + VT<T>::V;
        Tr.resize((size_t)stride);
        gS.resize((size_t)stride);
        gATf.resize((size_t)stride);
        last.resize((size_t)stride);
        gC.resize((size_t)stride * NC);
        accf.resize((size_t)NC);
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
            Tr[p] = A.out_T[q];
            gATf[p] = A.g_alpha[q] * A.out_T[q];
            last[p] = A.out_last[q];
            rowmax[jj] = std::max<int64_t>(rowmax[jj], A.out_last[q]);
            for (int c = 0; c < NC; ++c) gC[(size_t)c * ST + p] = A.g_acc[q * NC + c];
        }
        kmax = std::max<int64_t>(kmax, rowmax[jj]);
    }
    for (int64_t k = std::max(kmax + 1, k0); k < k1; ++k) std::memset(A.pair + (size_t)k * PS, 0, sizeof(T) * PS);
    const vT vzero = vT{}, vone = vT{} + (T)1, vhalf = vT{} + (T)0.5;
    const vT vamin = vT{} + (T)kAlphaMin, vamax = vT{} + (T)kAlphaMax;
    const vT lanef = lane_index<vT, V>();
    const vM lanei = lane_index<vM, V>();
    T fc[NCT > 0 ? NCT : 1];
    vT accf_fixed[NCT > 0 ? NCT : 1];
    vT *accf = NCT > 0 ? accf_fixed : S.accf.data();
    for (int64_t k = kmax; k >= k0; --k) {
        const int32_t g = A.isect[k];
        if (k - 2 >= k0) {
            __builtin_prefetch(A.splats + A.isect[k - 2]);
            __builtin_prefetch(A.feats + (size_t)A.isect[k - 2] * NC);
        }
        const vM vk = vM{} + (IT)k;
        const Splat<T> s = A.splats[g];
        const T *f = A.feats + (size_t)g * NC;
        if (NCT > 0)
            for (int c = 0; c < NCT; ++c) fc[c] = f[c];
        vT amx = vzero, amy = vzero, aa = vzero, ab = vzero, ac = vzero, ao = vzero;
        for (int c = 0; c < NC; ++c) accf[c] = vzero;
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
                    for (int c = 0; c < NCT; ++c) dot += fc[c] * vload<vT>(gC + (size_t)c * ST + p);
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
                for (int c = 0; c < NC; ++c) accf[c] += wa * vload<vT>(gC + (size_t)c * ST + p);
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
            for (int l = 0; l < V; ++l) sum += accf[c][l];
            pr[6 + c] = sum;
        }
    }
}
// One clone-able tile function per (type, channel count): the bodies are inlined
// into each clone, so the AVX2 clone is compiled with AVX2; the per-tile call
// goes through the ifunc resolved at load time.
#define MOGAF_TILE_FNS(T, SUF, NCT)                                                                              \
    MOGAF_CLONES void fwd_tile_##SUF##_##NCT(const FwdArgs<T> &A, int64_t t, FwdScratch<T> &S) {                 \
        forward_tile_body<T, NCT>(A, t, S);                                                                      \
    }                                                                                                            \
    MOGAF_CLONES void bwd_tile_##SUF##_##NCT(const BwdArgs<T> &A, int64_t t, BwdScratch<T> &S) {                 \
        backward_tile_body<T, NCT>(A, t, S);                                                                     \
    }                                                                                                            \
    void fwd_tiles_##SUF##_##NCT(const FwdArgs<T> &A, int nthreads) {                                            \
        const int ntx = (A.W + A.TS - 1) / A.TS, nty = (A.H + A.TS - 1) / A.TS;                                  \
        const int64_t ntiles = (int64_t)ntx * nty;                                                               \
        const int nw = (int)std::max<int64_t>(1, std::min<int64_t>(nthreads, ntiles));                           \
        std::vector<FwdScratch<T>> S((size_t)nw);                                                                \
        for (auto &s : S) s.init(A.TS, A.NC);                                                                    \
        parallel_for(ntiles, nw, [&](int64_t t, int w) { fwd_tile_##SUF##_##NCT(A, t, S[(size_t)w]); });         \
    }                                                                                                            \
    void bwd_tiles_##SUF##_##NCT(const BwdArgs<T> &A, int nthreads) {                                            \
        const int ntx = (A.W + A.TS - 1) / A.TS, nty = (A.H + A.TS - 1) / A.TS;                                  \
        const int64_t ntiles = (int64_t)ntx * nty;                                                               \
        const int nw = (int)std::max<int64_t>(1, std::min<int64_t>(nthreads, ntiles));                           \
        std::vector<BwdScratch<T>> S((size_t)nw);                                                                \
        for (auto &s : S) s.init(A.TS, A.NC);                                                                    \
        parallel_for(ntiles, nw, [&](int64_t t, int w) { bwd_tile_##SUF##_##NCT(A, t, S[(size_t)w]); });        \
    }

MOGAF_TILE_FNS(float, f32, 0)
MOGAF_TILE_FNS(float, f32, 1)
MOGAF_TILE_FNS(float, f32, 2)
MOGAF_TILE_FNS(float, f32, 3)
MOGAF_TILE_FNS(float, f32, 4)
MOGAF_TILE_FNS(float, f32, 5)
MOGAF_TILE_FNS(float, f32, 6)
MOGAF_TILE_FNS(float, f32, 7)
MOGAF_TILE_FNS(float, f32, 8)
MOGAF_TILE_FNS(double, f64, 0)
MOGAF_TILE_FNS(double, f64, 4)

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
void fwd_tiles(const FwdArgs<double> &A, int nt) {
    if (A.NC == 4) fwd_tiles_f64_4(A, nt);
    else fwd_tiles_f64_0(A, nt);
}
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
void bwd_tiles(const BwdArgs<double> &A, int nt) {
    if (A.NC == 4) bwd_tiles_f64_4(A, nt);
    else bwd_tiles_f64_0(A, nt);
}

template <typename T>
int forward_impl(int64_t M, int NC, int W, int H, int TS, int nthreads, const void *splats, const T *feats,
                 const int64_t *tile_offsets, const int32_t *isect, T *out_acc, T *out_T, int32_t *out_last) {
    if (TS < 1 || TS > kMaxTile) return -3;
    FwdArgs<T> A{M, NC, W, H, TS, (const Splat<T> *)splats, feats, tile_offsets, isect, out_acc, out_T, out_last};
    fwd_tiles(A, nthreads);
    return 0;
}

template <typename T>
int backward_impl(int64_t M, int NC, int W, int H, int TS, int nthreads, const void *splats, const T *feats,
                  const int64_t *tile_offsets, const int32_t *isect, const T *out_T, const int32_t *out_last,
                  const T *g_acc, const T *g_alpha, T *pair, T *g_means2d, T *g_conics, T *g_opac, T *g_feats) {
    if (TS < 1 || TS > kMaxTile) return -3;
    BwdArgs<T> A{M,     NC,       W,     H,     TS,      (const Splat<T> *)splats, feats, tile_offsets, isect,
                 out_T, out_last, g_acc, g_alpha, pair};
    bwd_tiles(A, nthreads);
    // Deterministic reduction of the per-(tile, Gaussian) records.
    const int PS = 6 + NC;
    std::memset(g_means2d, 0, sizeof(T) * 2 * (size_t)M);
    std::memset(g_conics, 0, sizeof(T) * 3 * (size_t)M);
    std::memset(g_opac, 0, sizeof(T) * (size_t)M);
    std::memset(g_feats, 0, sizeof(T) * NC * (size_t)M);
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
        T *gfp = g_feats + g * NC;
        for (int c = 0; c < NC; ++c) gfp[c] += pr[6 + c];
    }
    return 0;
}

}  // namespace

// ---------------------------------------------------------------------------
// C ABI. Return values: >= 0 success (prepare: number of tile intersections),
// -1 out of memory, -2 other failure, -3 bad tile size. Arrays are C-contiguous.
//   prepare: splats (splat_bytes(M) bytes, out), order (M int32, out),
//            tile_offsets (ntiles + 1 int64, out)
//   fill:    isect (total int32, out): per tile, Gaussian ids front to back
//   forward: out_acc (H, W, NC), out_T (H, W) final transmittance, out_last (H, W)
//            index into isect of the last composited Gaussian (-1: none)
//   backward: pair (total, 6 + NC) scratch; gradients for means2d (M, 2),
//            conics (M, 3), opacities (M), feats (M, NC)
extern "C" {

int mogaf_raster_abi_version() { return 2; }

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
                                void *splats, int32_t *order, int64_t *tile_offsets) {                            \
        if (TS < 1 || TS > kMaxTile) return -3;                                                                   \
        MOGAF_GUARD(prepare_impl<T>(M, W, H, TS, nthreads, means2d, conics, opac, radii, depths,                  \
                                    (Splat<T> *)splats, order, tile_offsets))                                     \
    }                                                                                                             \
    int mogaf_fill_##SUF(int64_t M, int W, int H, int TS, const void *splats, const int32_t *order,               \
                         const int64_t *tile_offsets, int32_t *isect) {                                           \
        MOGAF_GUARD(fill_impl<T>(M, W, H, TS, (const Splat<T> *)splats, order, tile_offsets, isect))              \
    }                                                                                                             \
    int mogaf_forward_##SUF(int64_t M, int NC, int W, int H, int TS, int nthreads, const void *splats,            \
                            const T *feats, const int64_t *tile_offsets, const int32_t *isect, T *out_acc,        \
                            T *out_T, int32_t *out_last) {                                                        \
        MOGAF_GUARD(forward_impl<T>(M, NC, W, H, TS, nthreads, splats, feats, tile_offsets, isect, out_acc,       \
                                    out_T, out_last))                                                             \
    }                                                                                                             \
    int mogaf_backward_##SUF(int64_t M, int NC, int W, int H, int TS, int nthreads, const void *splats,           \
                             const T *feats, const int64_t *tile_offsets, const int32_t *isect, const T *out_T,   \
                             const int32_t *out_last, const T *g_acc, const T *g_alpha, T *pair, T *g_means2d,    \
                             T *g_conics, T *g_opac, T *g_feats) {                                                \
        MOGAF_GUARD(backward_impl<T>(M, NC, W, H, TS, nthreads, splats, feats, tile_offsets, isect, out_T,        \
                                     out_last, g_acc, g_alpha, pair, g_means2d, g_conics, g_opac, g_feats))       \
    }

MOGAF_DEFINE(f32, float)
MOGAF_DEFINE(f64, double)

}  // extern "C"
