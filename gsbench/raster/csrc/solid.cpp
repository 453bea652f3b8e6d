// gsbench tile rasterizer: the stochastic-solid median depth of GGGS (docs/methods/gggs.md §1-§2), a pass
// after the compositing (composite.cpp) over the same tile lists, for the `rade` kernel.
//
// Plain C ABI (called through ctypes). Payload layout: gsbench/raster/payload.py (rade: 9 l, 10-11 p/f).
// Per pixel, over the Gaussians the compositing blended (list position < last, alpha >= 1/255, as there):
// the Gaussian's peak alpha, its ray distance t* = l + (p/f)·(pixel − means2d) (the rade depth plane) and
// its 1D width 1/σ along the ray (`inv_sigma`, one per Gaussian). Its transmittance as a stochastic solid:
//     T_i(t) = √(1 − α g) before t*, (1 − α)/√(1 − α g) after it,  g = exp(−½ ((t − t*)/σ)²).
// Forward: the initial estimate is the t* of the last blended Gaussian whose transmittance before it is > ½
// (GGGS's MEDIAN_DEPTH_INIT); the interval [max(init − R, 0), max(init + R, 0)] is cut into SPLIT cells for
// `rounds` rounds, each keeping the cell where T = Π T_i crosses ½, then the crossing is interpolated linearly.
// No crossing (T > ½ at the far end or < ½ at the near end) or a final transmittance above
// `min_transmittance` gives t = 0. Backward (the implicit function): dt/dθ = −(∂ log T/∂θ)/(∂ log T/∂t) at
// the found t, with ½|∂ log T/∂t| taken at least 1e-7 (GGGS's clamp). The gradient reaches the payload
// columns mx, my, conic, opacity, l, p/f and `inv_sigma`; a clamped alpha (o·G > 0.99) passes none to o and G,
// as in the compositing. Determinism as composite.cpp: static (1) tile schedule, per-thread buffers summed in
// thread order.

#include "raster_common.h"

namespace {

constexpr int SPLIT = 8;  // cells per round (GGGS: 8)
constexpr int NPR = 15;   // rade payload columns
constexpr int NSG = NPR + 2;  // gradient slots: payload, inv_sigma, absgrad
// |t − t*|/σ beyond which g = exp(−½ δ²) < e⁻³⁰ ≈ 1e-13 is taken as 0: a Gaussian whose peak is that far from
// every sample of a round multiplies them all by 1 (peak behind them) or 1 − α (peak in front) without an
// exponential. The change to T is below 1e-13 relative: under float32's resolution, and within the float64 tests.
constexpr double FAR_SIGMAS = 7.745966692414834;  // √60

}  // namespace

extern "C" {

// Keep in sync with SolidArgs in gsbench/raster/abi.py (ctypes): 8-byte fields only.
struct SolidArgs {
    int64_t dtype, width, height, tiles_x, tiles_y, n_gauss, nthreads, rounds;
    double search_range, min_transmittance;
    const void* params;           // (N, 15) rade payload
    const void* bounds;           // (N, 4) alpha >= 1/255 pixel box
    const int32_t* tile_offsets;  // (tiles + 1)
    const int32_t* tile_list;     // (pairs)
    const int32_t* last;          // (H, W) from the compositing forward
    const void* T_final;          // (H, W) from the compositing forward
    const void* inv_sigma;        // (N,)
    void* out_t;                  // (H, W) ray distance where T = ½ (0: none)
    const void* g_t;              // (H, W) backward input
    void* grad_params;            // (N, 15) zero-initialised
    void* grad_inv_sigma;         // (N,) zero-initialised
    void* absgrad;                // (N,) zero-initialised
    int64_t pairs;                // out: pixel-Gaussian pairs evaluated
};

}  // extern "C"

namespace {

// One blended pair of a pixel, or v = false. t* in ray distance.
template <typename T>
struct SolidPair {
    T al, G, oG, dx, dy, tpk;
    bool v;
};

template <typename T>
inline SolidPair<T> solid_pair(const T* __restrict p, T px, T py, int kk, int lastk) {
    SolidPair<T> s;
    s.dx = px - p[P_MX];
    s.dy = py - p[P_MY];
    const T power = T(-0.5) * (p[P_CA] * s.dx * s.dx + p[P_CC] * s.dy * s.dy) - p[P_CB] * s.dx * s.dy;
    s.G = fexp<T>(std::max(power, T(-30)));
    s.oG = p[P_O] * s.G;
    s.al = std::min(T(0.99), s.oG);
    s.v = kk < lastk && power <= T(0) && s.al >= T(1.0 / 255.0);
    s.tpk = p[P_X] + p[P_X + 1] * s.dx + p[P_X + 2] * s.dy;
    return s;
}

// Visit every (pixel, Gaussian) pair of a tile whose pixel centre lies in the Gaussian's box, for list
// positions below maxlast: fn(i, kk, g, p, px, py).
template <typename T, typename F>
inline int64_t for_pairs(const SolidArgs& A, int tile, int maxlast, const T* P, const T* BND, F&& fn) {
    const int TX = (int)A.tiles_x, W = (int)A.width, H = (int)A.height;
    const int x0 = (tile % TX) * TS, y0 = (tile / TX) * TS;
    const int ncols = std::min(TS, W - x0), nrows = std::min(TS, H - y0);
    const int beg = A.tile_offsets[tile];
    int64_t pairs = 0;
    for (int kk = 0; kk < maxlast; ++kk) {
        const int g = A.tile_list[beg + kk];
        const T* p = P + (int64_t)g * NPR;
        const T* bnd = BND + (int64_t)g * 4;
        int r0, r1, q0, q1;
        row_range<T>(bnd[2], bnd[3], y0, nrows, r0, r1);
        row_range<T>(bnd[0], bnd[1], x0, ncols, q0, q1);
        for (int y = r0; y < r1; ++y)
            for (int x = q0; x < q1; ++x) {
                fn((y - y0) * TS + (x - x0), kk, g, p, T(x) + T(0.5), T(y) + T(0.5));
                ++pairs;
            }
    }
    return pairs;
}

template <typename T>
inline int tile_last(const SolidArgs& A, int tile, int32_t* lastk) {
    const int TX = (int)A.tiles_x, W = (int)A.width, H = (int)A.height;
    const int x0 = (tile % TX) * TS, y0 = (tile / TX) * TS;
    int maxlast = 0;
    for (int i = 0; i < TP; ++i) {
        const int lx = i % TS, ly = i / TS;
        const bool in = x0 + lx < W && y0 + ly < H;
        lastk[i] = in ? A.last[(int64_t)(y0 + ly) * W + x0 + lx] : 0;
        maxlast = std::max(maxlast, lastk[i]);
    }
    return maxlast;
}

// The blended pairs of each pixel of a tile, in list (depth) order: one walk with one exponential per pair;
// the search rounds and the backward then read these compact lists.
template <typename T>
struct PixelLists {
    std::vector<SolidPair<T>> pairs[TP];
    std::vector<int32_t> ids[TP];
    int64_t fill(const SolidArgs& A, int tile, int maxlast, const int32_t* lastk, const T* P, const T* BND) {
        for (int i = 0; i < TP; ++i) {
            pairs[i].clear();
            ids[i].clear();
        }
        return for_pairs<T>(A, tile, maxlast, P, BND, [&](int i, int kk, int g, const T* p, T px, T py) {
            const SolidPair<T> s = solid_pair<T>(p, px, py, kk, lastk[i]);
            if (!s.v) return;
            pairs[i].push_back(s);
            ids[i].push_back(g);
        });
    }
};

// One round of the search: T at the samples S0..S1 of [lo, hi] (SPLIT cells) into Tp, over a pixel's blended
// pairs. A pair whose peak lies FAR_SIGMAS widths behind every sample changes nothing; one whose peak lies that
// far in front multiplies every sample by 1 − α (collected in one product); the others are evaluated at each
// sample (a constant trip count, vectorised: fexp is the compositing's exponential, exact in float64).
template <typename T, int S0, int S1>
inline void search_round(const std::vector<SolidPair<T>>& ps, const int32_t* gs, const T* ISG, T lo, T hi,
                         T* __restrict Tp) {
    const T step = (hi - lo) / T(SPLIT);
    alignas(64) T acc[SPLIT + 1], ts[SPLIT + 1];
    for (int q = 0; q <= SPLIT; ++q) {
        acc[q] = T(1);
        ts[q] = lo + step * T(q);
    }
    T passed = T(1);  // Π (1 − α) of the pairs whose peak is in front of every sample
    const int n = (int)ps.size();
    for (int e = 0; e < n; ++e) {
        const SolidPair<T>& s = ps[e];
        const T isg = ISG[gs[e]];
        const T first = (ts[S0] - s.tpk) * isg, last = (ts[S1] - s.tpk) * isg;
        if (last < T(-FAR_SIGMAS)) continue;
        if (first > T(FAR_SIGMAS)) {
            passed *= T(1) - s.al;
            continue;
        }
        const T al = s.al, tpk = s.tpk, after = T(1) - al;
        const bool ball = isg > T(0);
#pragma omp simd
        for (int q = S0; q <= S1; ++q) {
            const T dl = (ts[q] - tpk) * isg;
            const T g = bsel<T>(ball, fexp<T>(std::max(T(-0.5) * dl * dl, T(-30))), T(0));
            const T om = T(1) - al * g;
            acc[q] *= bsel<T>(ts[q] > tpk, after, om) / std::sqrt(om);
        }
    }
    for (int q = S0; q <= S1; ++q) Tp[q] = acc[q] * passed;
}

template <typename T>
void solid_forward(SolidArgs& A) {
    const int W = (int)A.width, H = (int)A.height, ntiles = (int)(A.tiles_x * A.tiles_y);
    const T* P = (const T*)A.params;
    const T* BND = (const T*)A.bounds;
    const T* ISG = (const T*)A.inv_sigma;
    const T* TF = (const T*)A.T_final;
    T* out = (T*)A.out_t;
    const T R = (T)A.search_range, minT = (T)A.min_transmittance;
    const int rounds = (int)A.rounds;
    int64_t pairs = 0;
#pragma omp parallel num_threads((int)A.nthreads) reduction(+ : pairs)
    {
        int32_t lastk[TP];
        PixelLists<T> lists;
        T Tp[SPLIT + 1];
#pragma omp for schedule(dynamic, 1)
        for (int tile = 0; tile < ntiles; ++tile) {
            const int TX = (int)A.tiles_x, x0 = (tile % TX) * TS, y0 = (tile / TX) * TS;
            const int maxlast = tile_last<T>(A, tile, lastk);
            pairs += lists.fill(A, tile, maxlast, lastk, P, BND);
            for (int i = 0; i < TP; ++i) {
                const int lx = i % TS, ly = i / TS;
                if (x0 + lx >= W || y0 + ly >= H) continue;
                const int64_t pix = (int64_t)(y0 + ly) * W + x0 + lx;
                const auto& ps = lists.pairs[i];
                const auto& gs = lists.ids[i];
                const int n = (int)ps.size();
                // the initial estimate: t* of the last blended Gaussian with T > ½ before it
                T Trun = T(1), init = T(0);
                for (int e = 0; e < n; ++e) {
                    if (Trun > T(0.5)) init = ps[e].tpk;
                    Trun *= T(1) - ps[e].al;
                }
                bool inr = n > 0 && TF[pix] <= minT;
                T lo = std::max(init - R, T(0)), hi = std::max(init + R, T(0));
                for (int round = 0; round < rounds && inr; ++round) {
                    if (round == 0) {
                        search_round<T, 0, SPLIT>(ps, gs.data(), ISG, lo, hi, Tp);
                        inr = Tp[0] >= T(0.5) && Tp[SPLIT] <= T(0.5);
                    } else {
                        search_round<T, 1, SPLIT - 1>(ps, gs.data(), ISG, lo, hi, Tp);
                    }
                    int start = 0;
                    for (int q = 1; q < SPLIT; ++q) start = Tp[q] >= T(0.5) ? q : start;
                    const T step = (hi - lo) / T(SPLIT), a = Tp[start], b = Tp[start + 1], base = lo;
                    lo = base + step * T(start);
                    hi = base + step * T(start + 1);
                    Tp[0] = a;
                    Tp[SPLIT] = b;
                }
                const T den = Tp[0] - Tp[SPLIT];
                const T w = den > T(0) ? std::min(std::max((Tp[0] - T(0.5)) / den, T(0)), T(1)) : T(0);
                out[pix] = inr ? w * hi + (T(1) - w) * lo : T(0);
            }
        }
    }
    A.pairs = pairs;
}

template <typename T>
void solid_backward(SolidArgs& A) {
    const int W = (int)A.width, H = (int)A.height, ntiles = (int)(A.tiles_x * A.tiles_y);
    const int64_t N = A.n_gauss;
    const T* P = (const T*)A.params;
    const T* BND = (const T*)A.bounds;
    const T* ISG = (const T*)A.inv_sigma;
    const T* OT = (const T*)A.out_t;
    const T* GT = (const T*)A.g_t;
    const T halfW = T(0.5) * W, halfH = T(0.5) * H;
    const int nthreads = std::max(1, (int)A.nthreads);
    std::vector<std::vector<T>> bufs(nthreads);
    int64_t pairs = 0;
#pragma omp parallel num_threads(nthreads) reduction(+ : pairs)
    {
        const int tid = omp_get_thread_num();
        std::vector<T>& buf = bufs[tid];
        buf.assign((size_t)N * NSG, T(0));
        int32_t lastk[TP];
        PixelLists<T> lists;
#pragma omp for schedule(static, 1)
        for (int tile = 0; tile < ntiles; ++tile) {
            const int TX = (int)A.tiles_x, x0 = (tile % TX) * TS, y0 = (tile / TX) * TS;
            bool any = false;
            for (int i = 0; i < TP && !any; ++i) {
                const int lx = i % TS, ly = i / TS;
                const int64_t pix = (int64_t)(y0 + ly) * W + x0 + lx;
                any = x0 + lx < W && y0 + ly < H && OT[pix] != T(0) && GT[pix] != T(0);
            }
            if (!any) continue;
            const int maxlast = tile_last<T>(A, tile, lastk);
            pairs += lists.fill(A, tile, maxlast, lastk, P, BND);
            for (int i = 0; i < TP; ++i) {
                const int lx = i % TS, ly = i / TS;
                if (x0 + lx >= W || y0 + ly >= H) continue;
                const int64_t pix = (int64_t)(y0 + ly) * W + x0 + lx;
                const T tm = OT[pix], gt = GT[pix];
                if (tm == T(0) || gt == T(0)) continue;
                const auto& ps = lists.pairs[i];
                const auto& gs = lists.ids[i];
                const int n = (int)ps.size();
                // ½ ∂ log T/∂t at the found t (GGGS's dT_dtm), then c = g / max(−that, 1e-7)
                T slope = T(0);
                for (int e = 0; e < n; ++e) {
                    const T isg = ISG[gs[e]], dl = (tm - ps[e].tpk) * isg;
                    if (std::fabs(dl) > T(FAR_SIGMAS)) continue;
                    const T Gt = ps[e].al * std::exp(T(-0.5) * dl * dl);
                    slope += T(-0.25) * Gt / (T(1) - Gt) * std::fabs(dl) * isg;
                }
                const T c = gt / std::max(-slope, T(1e-7));
                for (int e = 0; e < n; ++e) {
                    const SolidPair<T>& s = ps[e];
                    const int g = gs[e];
                    const T* p = P + (int64_t)g * NPR;
                    const T isg = ISG[g], dt = tm - s.tpk, dl = dt * isg;
                    const T Ge = std::fabs(dl) > T(FAR_SIGMAS) ? T(0) : std::exp(T(-0.5) * dl * dl), Gt = s.al * Ge;
                    T dGt = c * T(0.25) / (T(1) - Gt);
                    dGt = tm > s.tpk ? dGt : -dGt;
                    dGt = isg > T(0) ? dGt : T(0);
                    const T dal = dGt * Ge - (dl > T(0) ? c * T(0.5) / (T(1) - s.al) : T(0));
                    const T ddl = -dGt * Gt * dl;
                    const T dtpk = -ddl * isg;
                    T* gp = buf.data() + (int64_t)g * NSG;
                    gp[NPR] += ddl * dt;  // inv_sigma
                    T gmx = T(0), gmy = T(0);
                    if (s.oG <= T(0.99)) {  // alpha not clamped: its gradient reaches o and G
                        gp[P_O] += s.G * dal;
                        const T gG = p[P_O] * dal * s.G;
                        gmx = gG * (p[P_CA] * s.dx + p[P_CB] * s.dy);
                        gmy = gG * (p[P_CB] * s.dx + p[P_CC] * s.dy);
                        gp[P_CA] += T(-0.5) * gG * s.dx * s.dx;
                        gp[P_CB] += -gG * s.dx * s.dy;
                        gp[P_CC] += T(-0.5) * gG * s.dy * s.dy;
                    }
                    gp[P_X] += dtpk;
                    gp[P_X + 1] += dtpk * s.dx;
                    gp[P_X + 2] += dtpk * s.dy;
                    gmx -= dtpk * p[P_X + 1];
                    gmy -= dtpk * p[P_X + 2];
                    gp[P_MX] += gmx;
                    gp[P_MY] += gmy;
                    gp[NPR + 1] += std::fabs(gmx) * halfW + std::fabs(gmy) * halfH;
                }
            }
        }
    }
    T* gp = (T*)A.grad_params;
    T* gs = (T*)A.grad_inv_sigma;
    T* ga = (T*)A.absgrad;
    for (const auto& b : bufs)  // thread order: bit-identical from run to run at a given thread count
        for (int64_t g = 0; g < N; ++g) {
            const T* row = b.data() + g * NSG;
            for (int k = 0; k < NPR; ++k) gp[g * NPR + k] += row[k];
            gs[g] += row[NPR];
            ga[g] += row[NPR + 1];
        }
    A.pairs = pairs;
}

}  // namespace

extern "C" {

int gs_solid_forward(SolidArgs* A) {
    if (A->rounds < 1) return -2;
    A->dtype == 0 ? solid_forward<float>(*A) : solid_forward<double>(*A);
    return 0;
}

int gs_solid_backward(SolidArgs* A) {
    A->dtype == 0 ? solid_backward<float>(*A) : solid_backward<double>(*A);
    return 0;
}

}  // extern "C"
