// Tile-based CPU rasterizer for projected 3D Gaussians (3DGS / EWA compositing)
// with the analytic backward pass.
//
// Plain C++17 + std::thread: no torch headers (they take ~40 s to compile), no
// OpenMP (its runtime is not fork-safe and may be absent). Loaded with ctypes by
// mogaf/render/cpu.py, which owns every buffer (so torch accounts for memory).
//
// Semantics (identical to mogaf.render.reference.composite_dense):
//   pixel (i, j) has centre (i + 0.5, j + 0.5); Gaussian g touches it iff the
//   centre lies in the closed box |mx - px| <= rx, |my - py| <= ry, and
//   sigma = 0.5 (a dx^2 + c dy^2) + b dx dy >= 0 (dx = mx - px, dy = my - py),
//   alpha = min(0.99, o exp(-sigma)) >= 1/255.  Gaussians are composited front
//   to back in the order given by the caller (depth, ties by index); a pixel
//   stops at the first Gaussian that would bring its transmittance to <= 1e-4
//   (that Gaussian is not composited), as in 3DGS / gsplat.
//
// Tiles only organise the work: the result does not depend on the tile size.
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <exception>
#include <new>
#include <thread>
#include <vector>

namespace {

constexpr double kAlphaMin = 1.0 / 255.0;
constexpr double kAlphaMax = 0.99;
constexpr double kTMin = 1e-4;

// Run fn(item, worker) for item in [0, n) on up to nthreads threads, items
// handed out dynamically (tiles have very uneven cost).
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

template <typename T>
struct Splat {
    T mx, my, a, b, c, o, rx, ry;
    double tau;  // relaxed bound on sigma (alpha >= 1/255 implies sigma <= tau)
    double det;  // a c - b^2 of the conic
    int i0, i1, j0, j1;  // inclusive pixel box clipped to the image
};

template <typename T>
inline bool in_box(T m, T r, int i) {
    T d = m - ((T)i + (T)0.5);
    return std::abs(d) <= r;
}

// Pixels i in [0, n) whose centre satisfies |m - (i + 0.5)| <= r, evaluated
// exactly as the inner loops and the torch reference evaluate it.
template <typename T>
inline void box_range(T m, T r, int n, int &lo, int &hi) {
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
inline Splat<T> make_splat(int64_t g, int W, int H, const T *means2d, const T *conics,
                           const T *opac, const int32_t *radii) {
    Splat<T> s;
    s.mx = means2d[2 * g];
    s.my = means2d[2 * g + 1];
    s.a = conics[3 * g];
    s.b = conics[3 * g + 1];
    s.c = conics[3 * g + 2];
    s.o = opac[g];
    s.rx = (T)radii[2 * g];
    s.ry = (T)radii[2 * g + 1];
    s.det = (double)s.a * (double)s.c - (double)s.b * (double)s.b;
    double o = (double)s.o;
    bool ok = std::isfinite((double)s.mx) && std::isfinite((double)s.my) && std::isfinite((double)s.a) &&
              std::isfinite((double)s.b) && std::isfinite((double)s.c) && o * 255.0 >= 1.0 &&
              radii[2 * g] >= 0 && radii[2 * g + 1] >= 0;
    if (!ok) {
        s.tau = -1.0;
        s.i0 = s.j0 = 0;
        s.i1 = s.j1 = -1;
        return s;
    }
    double tau = std::log(255.0 * o);
    s.tau = tau * (1.0 + 1e-4) + 1e-3;
    box_range(s.mx, s.rx, W, s.i0, s.i1);
    box_range(s.my, s.ry, H, s.j0, s.j1);
    return s;
}

// Columns of row j (clipped to the box) that may have alpha >= 1/255.
template <typename T>
inline bool row_span(const Splat<T> &s, int j, int &ia, int &ib) {
    ia = s.i0;
    ib = s.i1;
    if (ia > ib) return false;
    double a = (double)s.a;
    if (!(s.det > 0.0) || !(a > 0.0)) return true;  // degenerate conic: whole box row
    double dy = (double)s.my - ((double)j + 0.5);
    double disc = 2.0 * a * s.tau - s.det * dy * dy;
    if (disc < 0.0) return false;
    double sq = std::sqrt(disc);
    double bdy = (double)s.b * dy;
    double dx_lo = (-bdy - sq) / a, dx_hi = (-bdy + sq) / a;
    double lo = std::ceil((double)s.mx - dx_hi - 0.5);
    double hi = std::floor((double)s.mx - dx_lo - 0.5);
    if (lo > (double)ia) ia = (lo > (double)ib) ? ib + 1 : (int)lo;
    if (hi < (double)ib) ib = (hi < (double)ia) ? ia - 1 : (int)hi;
    return ia <= ib;
}

inline double seg_min(double a, double b, double c, double fixed, double lo, double hi, bool fixed_is_dy) {
    // min over the free coordinate in [lo, hi] of 0.5 a dx^2 + b dx dy + 0.5 c dy^2
    if (fixed_is_dy) {
        double dy = fixed;
        double dx = a > 0.0 ? -b * dy / a : 0.0;
        dx = std::min(std::max(dx, lo), hi);
        return 0.5 * a * dx * dx + b * dx * dy + 0.5 * c * dy * dy;
    }
    double dx = fixed;
    double dy = c > 0.0 ? -b * dx / c : 0.0;
    dy = std::min(std::max(dy, lo), hi);
    return 0.5 * a * dx * dx + b * dx * dy + 0.5 * c * dy * dy;
}

// Does the relaxed ellipse reach a pixel centre of columns [c0, c1] x rows [r0, r1]?
template <typename T>
inline bool hits_rect(const Splat<T> &s, int c0, int c1, int r0, int r1) {
    if (!(s.det > 0.0)) return true;
    double mx = (double)s.mx, my = (double)s.my;
    double dx_lo = mx - ((double)c1 + 0.5), dx_hi = mx - ((double)c0 + 0.5);
    double dy_lo = my - ((double)r1 + 0.5), dy_hi = my - ((double)r0 + 0.5);
    if (dx_lo <= 0.0 && dx_hi >= 0.0 && dy_lo <= 0.0 && dy_hi >= 0.0) return true;
    double a = (double)s.a, b = (double)s.b, c = (double)s.c;
    double m = seg_min(a, b, c, dy_lo, dx_lo, dx_hi, true);
    m = std::min(m, seg_min(a, b, c, dy_hi, dx_lo, dx_hi, true));
    m = std::min(m, seg_min(a, b, c, dx_lo, dy_lo, dy_hi, false));
    m = std::min(m, seg_min(a, b, c, dx_hi, dy_lo, dy_hi, false));
    return m <= s.tau * (1.0 + 1e-6) + 1e-6;
}

template <typename T>
std::vector<Splat<T>> make_splats(int64_t M, int W, int H, const T *means2d, const T *conics,
                                  const T *opac, const int32_t *radii) {
    std::vector<Splat<T>> splats((size_t)M);
    for (int64_t g = 0; g < M; ++g) splats[(size_t)g] = make_splat(g, W, H, means2d, conics, opac, radii);
    return splats;
}

// Visit the tiles a splat may touch (ellipse-tested), in row-major tile order.
template <typename T, typename F>
inline void for_each_tile(const Splat<T> &s, int TS, int ntx, F &&fn) {
    if (s.i0 > s.i1 || s.j0 > s.j1) return;
    int tx0 = s.i0 / TS, tx1 = s.i1 / TS, ty0 = s.j0 / TS, ty1 = s.j1 / TS;
    bool single = (tx0 == tx1 && ty0 == ty1);
    for (int ty = ty0; ty <= ty1; ++ty) {
        int r0 = std::max(ty * TS, s.j0), r1 = std::min(ty * TS + TS - 1, s.j1);
        for (int tx = tx0; tx <= tx1; ++tx) {
            int c0 = std::max(tx * TS, s.i0), c1 = std::min(tx * TS + TS - 1, s.i1);
            if (single || hits_rect(s, c0, c1, r0, r1)) fn(ty * ntx + tx);
        }
    }
}

template <typename T>
int64_t bin_impl(int64_t M, int W, int H, int TS, const T *means2d, const T *conics, const T *opac,
                 const int32_t *radii, const int64_t *order, int64_t *tile_offsets, int32_t *isect) {
    int ntx = (W + TS - 1) / TS, nty = (H + TS - 1) / TS;
    int64_t ntiles = (int64_t)ntx * nty;
    std::vector<Splat<T>> splats = make_splats(M, W, H, means2d, conics, opac, radii);
    if (isect == nullptr) {
        std::vector<int64_t> counts((size_t)ntiles, 0);
        for (int64_t g = 0; g < M; ++g)
            for_each_tile(splats[(size_t)g], TS, ntx, [&](int64_t t) { counts[(size_t)t]++; });
        int64_t total = 0;
        for (int64_t t = 0; t < ntiles; ++t) {
            tile_offsets[t] = total;
            total += counts[(size_t)t];
        }
        tile_offsets[ntiles] = total;
        return total;
    }
    std::vector<int64_t> cursor(tile_offsets, tile_offsets + ntiles);
    for (int64_t r = 0; r < M; ++r) {
        int64_t g = order[r];
        for_each_tile(splats[(size_t)g], TS, ntx, [&](int64_t t) { isect[cursor[(size_t)t]++] = (int32_t)g; });
    }
    return tile_offsets[ntiles];
}

template <typename T, int NCT>
void forward_impl(int64_t M, int NC_rt, int W, int H, int TS, int nthreads, const T *means2d, const T *conics,
                  const T *opac, const T *feats, const int32_t *radii, const int64_t *tile_offsets,
                  const int32_t *isect, T *out_acc, T *out_T, int32_t *out_last) {
    const int NC = NCT > 0 ? NCT : NC_rt;
    int ntx = (W + TS - 1) / TS, nty = (H + TS - 1) / TS;
    int64_t ntiles = (int64_t)ntx * nty;
    std::vector<Splat<T>> splats = make_splats(M, W, H, means2d, conics, opac, radii);
    int nw = std::max(1, std::min<int>(nthreads, (int)std::max<int64_t>(ntiles, 1)));
    const size_t tp = (size_t)TS * TS;
    std::vector<T> s_T(tp * nw), s_acc(tp * NC * nw);
    std::vector<int32_t> s_last(tp * nw);
    std::vector<uint8_t> s_done(tp * nw);
    const T amin = (T)kAlphaMin, amax = (T)kAlphaMax, tmin = (T)kTMin, half = (T)0.5, one = (T)1;

    parallel_for(ntiles, nw, [&](int64_t t, int w) {
        T *Tr = s_T.data() + tp * w;
        T *acc = s_acc.data() + tp * NC * w;
        int32_t *last = s_last.data() + tp * w;
        uint8_t *done = s_done.data() + tp * w;
        const int tx = (int)(t % ntx), ty = (int)(t / ntx);
        const int px0 = tx * TS, py0 = ty * TS;
        const int tw = std::min(TS, W - px0), th = std::min(TS, H - py0);
        for (int jj = 0; jj < th; ++jj)
            for (int ii = 0; ii < tw; ++ii) {
                int p = jj * TS + ii;
                Tr[p] = one;
                last[p] = -1;
                done[p] = 0;
                for (int c = 0; c < NC; ++c) acc[(size_t)p * NC + c] = (T)0;
            }
        const int npix = tw * th;
        int ndone = 0;
        const int64_t k0 = tile_offsets[t], k1 = tile_offsets[t + 1];
        for (int64_t k = k0; k < k1 && ndone < npix; ++k) {
            const int32_t g = isect[k];
            const Splat<T> &s = splats[(size_t)g];
            const T *f = feats + (size_t)g * NC;
            const int jlo = std::max(s.j0, py0), jhi = std::min(s.j1, py0 + th - 1);
            for (int j = jlo; j <= jhi; ++j) {
                int ia, ib;
                if (!row_span(s, j, ia, ib)) continue;
                ia = std::max(ia, px0);
                ib = std::min(ib, px0 + tw - 1);
                const T dy = s.my - ((T)j + half);
                for (int i = ia; i <= ib; ++i) {
                    const int p = (j - py0) * TS + (i - px0);
                    if (done[p]) continue;
                    const T dx = s.mx - ((T)i + half);
                    const T sigma = half * (s.a * dx * dx + s.c * dy * dy) + s.b * dx * dy;
                    if (sigma < (T)0) continue;
                    const T alpha = std::min(amax, s.o * std::exp(-sigma));
                    if (alpha < amin) continue;
                    const T Tp = Tr[p];
                    const T nT = Tp * (one - alpha);
                    if (nT <= tmin) {
                        done[p] = 1;
                        ++ndone;
                        continue;
                    }
                    const T wgt = alpha * Tp;
                    T *ap = acc + (size_t)p * NC;
                    for (int c = 0; c < NC; ++c) ap[c] += wgt * f[c];
                    Tr[p] = nT;
                    last[p] = (int32_t)k;
                }
            }
        }
        for (int jj = 0; jj < th; ++jj)
            for (int ii = 0; ii < tw; ++ii) {
                const int p = jj * TS + ii;
                const size_t q = (size_t)(py0 + jj) * W + (px0 + ii);
                out_T[q] = Tr[p];
                out_last[q] = last[p];
                for (int c = 0; c < NC; ++c) out_acc[q * NC + c] = acc[(size_t)p * NC + c];
            }
    });
}

template <typename T, int NCT>
void backward_impl(int64_t M, int NC_rt, int W, int H, int TS, int nthreads, const T *means2d, const T *conics,
                   const T *opac, const T *feats, const int32_t *radii, const int64_t *tile_offsets,
                   const int32_t *isect, const T *out_T, const int32_t *out_last, const T *g_acc,
                   const T *g_alpha, T *pair, T *g_means2d, T *g_conics, T *g_opac, T *g_feats) {
    const int NC = NCT > 0 ? NCT : NC_rt;
    const int PS = 6 + NC;  // per-pair gradient record: mx, my, a, b, c, o, features
    int ntx = (W + TS - 1) / TS, nty = (H + TS - 1) / TS;
    int64_t ntiles = (int64_t)ntx * nty;
    std::vector<Splat<T>> splats = make_splats(M, W, H, means2d, conics, opac, radii);
    int nw = std::max(1, std::min<int>(nthreads, (int)std::max<int64_t>(ntiles, 1)));
    const size_t tp = (size_t)TS * TS;
    std::vector<T> s_T(tp * nw), s_gS(tp * nw), s_gATf(tp * nw), s_gC(tp * NC * nw), s_gf((size_t)NC * nw);
    std::vector<int32_t> s_last(tp * nw);
    const T amin = (T)kAlphaMin, amax = (T)kAlphaMax, half = (T)0.5, one = (T)1;

    parallel_for(ntiles, nw, [&](int64_t t, int w) {
        T *Tr = s_T.data() + tp * w;
        T *gS = s_gS.data() + tp * w;
        T *gATf = s_gATf.data() + tp * w;
        T *gC = s_gC.data() + tp * NC * w;
        T *gf = s_gf.data() + (size_t)NC * w;
        int32_t *last = s_last.data() + tp * w;
        const int tx = (int)(t % ntx), ty = (int)(t / ntx);
        const int px0 = tx * TS, py0 = ty * TS;
        const int tw = std::min(TS, W - px0), th = std::min(TS, H - py0);
        const int64_t k0 = tile_offsets[t], k1 = tile_offsets[t + 1];
        int64_t kmax = k0 - 1;
        for (int jj = 0; jj < th; ++jj)
            for (int ii = 0; ii < tw; ++ii) {
                const int p = jj * TS + ii;
                const size_t q = (size_t)(py0 + jj) * W + (px0 + ii);
                Tr[p] = out_T[q];
                gS[p] = (T)0;
                gATf[p] = g_alpha[q] * out_T[q];
                last[p] = out_last[q];
                kmax = std::max<int64_t>(kmax, out_last[q]);
                for (int c = 0; c < NC; ++c) gC[(size_t)p * NC + c] = g_acc[q * NC + c];
            }
        for (int64_t k = kmax + 1; k < k1; ++k)
            std::memset(pair + (size_t)k * PS, 0, sizeof(T) * PS);
        for (int64_t k = kmax; k >= k0; --k) {
            const int32_t g = isect[k];
            const Splat<T> &s = splats[(size_t)g];
            const T *f = feats + (size_t)g * NC;
            T gmx = 0, gmy = 0, ga = 0, gb = 0, gc = 0, go = 0;
            for (int c = 0; c < NC; ++c) gf[c] = (T)0;
            const int jlo = std::max(s.j0, py0), jhi = std::min(s.j1, py0 + th - 1);
            for (int j = jlo; j <= jhi; ++j) {
                int ia, ib;
                if (!row_span(s, j, ia, ib)) continue;
                ia = std::max(ia, px0);
                ib = std::min(ib, px0 + tw - 1);
                const T dy = s.my - ((T)j + half);
                for (int i = ia; i <= ib; ++i) {
                    const int p = (j - py0) * TS + (i - px0);
                    if (last[p] < k) continue;
                    const T dx = s.mx - ((T)i + half);
                    const T sigma = half * (s.a * dx * dx + s.c * dy * dy) + s.b * dx * dy;
                    if (sigma < (T)0) continue;
                    const T G = std::exp(-sigma);
                    const T raw = s.o * G;
                    const T alpha = std::min(amax, raw);
                    if (alpha < amin) continue;
                    const T om = one - alpha;
                    const T Ti = Tr[p] / om;
                    const T wgt = alpha * Ti;
                    const T *gcp = gC + (size_t)p * NC;
                    T dot = (T)0;
                    for (int c = 0; c < NC; ++c) {
                        dot += f[c] * gcp[c];
                        gf[c] += wgt * gcp[c];
                    }
                    const T dLda = Ti * dot - (gS[p] - gATf[p]) / om;
                    gS[p] += wgt * dot;
                    Tr[p] = Ti;
                    if (raw < amax) {
                        go += G * dLda;
                        const T dLds = -alpha * dLda;
                        ga += half * dx * dx * dLds;
                        gb += dx * dy * dLds;
                        gc += half * dy * dy * dLds;
                        gmx += (s.a * dx + s.b * dy) * dLds;
                        gmy += (s.b * dx + s.c * dy) * dLds;
                    }
                }
            }
            T *pr = pair + (size_t)k * PS;
            pr[0] = gmx;
            pr[1] = gmy;
            pr[2] = ga;
            pr[3] = gb;
            pr[4] = gc;
            pr[5] = go;
            for (int c = 0; c < NC; ++c) pr[6 + c] = gf[c];
        }
    });

    // Deterministic reduction of the per-(tile, Gaussian) records.
    std::memset(g_means2d, 0, sizeof(T) * 2 * (size_t)M);
    std::memset(g_conics, 0, sizeof(T) * 3 * (size_t)M);
    std::memset(g_opac, 0, sizeof(T) * (size_t)M);
    std::memset(g_feats, 0, sizeof(T) * NC * (size_t)M);
    const int64_t n_isect = tile_offsets[ntiles];
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
}

template <typename T>
int forward_dispatch(int64_t M, int NC, int W, int H, int TS, int nthreads, const T *means2d, const T *conics,
                     const T *opac, const T *feats, const int32_t *radii, const int64_t *tile_offsets,
                     const int32_t *isect, T *out_acc, T *out_T, int32_t *out_last) {
#define MOGAF_FWD(NCT) \
    forward_impl<T, NCT>(M, NC, W, H, TS, nthreads, means2d, conics, opac, feats, radii, tile_offsets, isect, \
                         out_acc, out_T, out_last)
    switch (NC) {
        case 1: MOGAF_FWD(1); break;
        case 2: MOGAF_FWD(2); break;
        case 3: MOGAF_FWD(3); break;
        case 4: MOGAF_FWD(4); break;
        case 5: MOGAF_FWD(5); break;
        case 6: MOGAF_FWD(6); break;
        case 7: MOGAF_FWD(7); break;
        case 8: MOGAF_FWD(8); break;
        default: MOGAF_FWD(0); break;
    }
#undef MOGAF_FWD
    return 0;
}

template <typename T>
int backward_dispatch(int64_t M, int NC, int W, int H, int TS, int nthreads, const T *means2d, const T *conics,
                      const T *opac, const T *feats, const int32_t *radii, const int64_t *tile_offsets,
                      const int32_t *isect, const T *out_T, const int32_t *out_last, const T *g_acc,
                      const T *g_alpha, T *pair, T *g_means2d, T *g_conics, T *g_opac, T *g_feats) {
#define MOGAF_BWD(NCT) \
    backward_impl<T, NCT>(M, NC, W, H, TS, nthreads, means2d, conics, opac, feats, radii, tile_offsets, isect, \
                          out_T, out_last, g_acc, g_alpha, pair, g_means2d, g_conics, g_opac, g_feats)
    switch (NC) {
        case 1: MOGAF_BWD(1); break;
        case 2: MOGAF_BWD(2); break;
        case 3: MOGAF_BWD(3); break;
        case 4: MOGAF_BWD(4); break;
        case 5: MOGAF_BWD(5); break;
        case 6: MOGAF_BWD(6); break;
        case 7: MOGAF_BWD(7); break;
        case 8: MOGAF_BWD(8); break;
        default: MOGAF_BWD(0); break;
    }
#undef MOGAF_BWD
    return 0;
}

}  // namespace

// ---------------------------------------------------------------------------
// C ABI. Return values: >= 0 success (bin: number of intersections), -1 out of
// memory, -2 other failure. All arrays are C-contiguous; see cpu.py.
extern "C" {

int mogaf_raster_abi_version() { return 1; }

#define MOGAF_GUARD(expr)                 \
    try {                                 \
        return (expr);                    \
    } catch (const std::bad_alloc &) {    \
        return -1;                        \
    } catch (...) {                       \
        return -2;                        \
    }

#define MOGAF_DEFINE(SUF, T)                                                                                      \
    int64_t mogaf_bin_##SUF(int64_t M, int W, int H, int TS, const T *means2d, const T *conics, const T *opac,     \
                            const int32_t *radii, const int64_t *order, int64_t *tile_offsets, int32_t *isect) {  \
        MOGAF_GUARD(bin_impl<T>(M, W, H, TS, means2d, conics, opac, radii, order, tile_offsets, isect))            \
    }                                                                                                             \
    int mogaf_forward_##SUF(int64_t M, int NC, int W, int H, int TS, int nthreads, const T *means2d,              \
                            const T *conics, const T *opac, const T *feats, const int32_t *radii,                 \
                            const int64_t *tile_offsets, const int32_t *isect, T *out_acc, T *out_T,              \
                            int32_t *out_last) {                                                                  \
        MOGAF_GUARD(forward_dispatch<T>(M, NC, W, H, TS, nthreads, means2d, conics, opac, feats, radii,           \
                                        tile_offsets, isect, out_acc, out_T, out_last))                           \
    }                                                                                                             \
    int mogaf_backward_##SUF(int64_t M, int NC, int W, int H, int TS, int nthreads, const T *means2d,             \
                             const T *conics, const T *opac, const T *feats, const int32_t *radii,                \
                             const int64_t *tile_offsets, const int32_t *isect, const T *out_T,                   \
                             const int32_t *out_last, const T *g_acc, const T *g_alpha, T *pair, T *g_means2d,    \
                             T *g_conics, T *g_opac, T *g_feats) {                                                \
        MOGAF_GUARD(backward_dispatch<T>(M, NC, W, H, TS, nthreads, means2d, conics, opac, feats, radii,          \
                                         tile_offsets, isect, out_T, out_last, g_acc, g_alpha, pair, g_means2d,   \
                                         g_conics, g_opac, g_feats))                                              \
    }

MOGAF_DEFINE(f32, float)
MOGAF_DEFINE(f64, double)

}  // extern "C"
