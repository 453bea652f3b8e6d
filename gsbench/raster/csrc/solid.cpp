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

}  // namespace

extern "C" {

// Keep in sync with SolidArgs in gsbench/raster/abi.py (ctypes): 8-byte fields only.
struct SolidArgs {
    int64_t dtype, width, height, tiles_x, tiles_y, n_gauss, nthreads, rounds;
    double fx, fy, cx, cy, search_range, min_transmittance;
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

// factor of T_i at t (the module comment)
template <typename T>
inline T solid_factor(T t, T al, T tpk, T isg) {
    const T dl = (t - tpk) * isg;
    const T g = isg > T(0) ? std::exp(T(-0.5) * dl * dl) : T(0);
    const T om = T(1) - al * g;
    return (t > tpk ? T(1) - al : om) / std::sqrt(om);
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
        T Trun[TP], init[TP], lo[TP], hi[TP], Tp[SPLIT + 1][TP];
        bool inr[TP];
#pragma omp for schedule(dynamic, 1)
        for (int tile = 0; tile < ntiles; ++tile) {
            const int TX = (int)A.tiles_x, x0 = (tile % TX) * TS, y0 = (tile / TX) * TS;
            const int maxlast = tile_last<T>(A, tile, lastk);
            for (int i = 0; i < TP; ++i) {
                Trun[i] = T(1);
                init[i] = T(0);
                Tp[0][i] = Tp[SPLIT][i] = T(1);
            }
            // the initial estimate: t* of the last blended Gaussian with T > ½ before it
            pairs += for_pairs<T>(A, tile, maxlast, P, BND, [&](int i, int kk, int, const T* p, T px, T py) {
                const SolidPair<T> s = solid_pair<T>(p, px, py, kk, lastk[i]);
                if (!s.v) return;
                if (Trun[i] > T(0.5)) init[i] = s.tpk;
                Trun[i] *= T(1) - s.al;
            });
            for (int i = 0; i < TP; ++i) {
                const int lx = i % TS, ly = i / TS;
                const bool in = x0 + lx < W && y0 + ly < H;
                lo[i] = std::max(init[i] - R, T(0));
                hi[i] = std::max(init[i] + R, T(0));
                inr[i] = in && lastk[i] > 0 && TF[(int64_t)(y0 + ly) * W + x0 + lx] <= minT;
            }
            for (int round = 0; round < rounds && maxlast > 0; ++round) {
                const int s0 = round == 0 ? 0 : 1, s1 = round == 0 ? SPLIT : SPLIT - 1;
                for (int s = s0; s <= s1; ++s)
                    for (int i = 0; i < TP; ++i) Tp[s][i] = T(1);
                pairs += for_pairs<T>(A, tile, maxlast, P, BND, [&](int i, int kk, int g, const T* p, T px, T py) {
                    if (!inr[i]) return;
                    const SolidPair<T> s = solid_pair<T>(p, px, py, kk, lastk[i]);
                    if (!s.v) return;
                    const T isg = ISG[g], step = (hi[i] - lo[i]) / T(SPLIT);
                    for (int q = s0; q <= s1; ++q) Tp[q][i] *= solid_factor<T>(lo[i] + step * T(q), s.al, s.tpk, isg);
                });
                for (int i = 0; i < TP; ++i) {
                    if (round == 0) inr[i] = inr[i] && Tp[0][i] >= T(0.5) && Tp[SPLIT][i] <= T(0.5);
                    int start = 0;
                    for (int q = 1; q < SPLIT; ++q) start = Tp[q][i] >= T(0.5) ? q : start;
                    const T step = (hi[i] - lo[i]) / T(SPLIT), base = lo[i];
                    lo[i] = base + step * T(start);
                    hi[i] = base + step * T(start + 1);
                    const T a = Tp[start][i], b = Tp[start + 1][i];
                    Tp[0][i] = a;
                    Tp[SPLIT][i] = b;
                }
            }
            for (int i = 0; i < TP; ++i) {
                const int lx = i % TS, ly = i / TS;
                if (x0 + lx >= W || y0 + ly >= H) continue;
                const T den = Tp[0][i] - Tp[SPLIT][i];
                const T w = den > T(0) ? std::min(std::max((Tp[0][i] - T(0.5)) / den, T(0)), T(1)) : T(0);
                out[(int64_t)(y0 + ly) * W + x0 + lx] = (inr[i] && maxlast > 0) ? w * hi[i] + (T(1) - w) * lo[i] : T(0);
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
        T tm[TP], gt[TP], c[TP];
#pragma omp for schedule(static, 1)
        for (int tile = 0; tile < ntiles; ++tile) {
            const int TX = (int)A.tiles_x, x0 = (tile % TX) * TS, y0 = (tile / TX) * TS;
            int maxlast = tile_last<T>(A, tile, lastk);
            bool any = false;
            for (int i = 0; i < TP; ++i) {
                const int lx = i % TS, ly = i / TS;
                const bool in = x0 + lx < W && y0 + ly < H;
                const int64_t pix = (int64_t)(y0 + ly) * W + x0 + lx;
                tm[i] = in ? OT[pix] : T(0);
                gt[i] = (in && tm[i] != T(0)) ? GT[pix] : T(0);
                c[i] = T(0);
                any = any || gt[i] != T(0);
            }
            if (!any) continue;
            // ½ ∂ log T/∂t at the found t (GGGS's dT_dtm), then c = g / max(−that, 1e-7)
            pairs += for_pairs<T>(A, tile, maxlast, P, BND, [&](int i, int kk, int g, const T* p, T px, T py) {
                if (gt[i] == T(0)) return;
                const SolidPair<T> s = solid_pair<T>(p, px, py, kk, lastk[i]);
                if (!s.v) return;
                const T isg = ISG[g], dl = (tm[i] - s.tpk) * isg;
                const T Gt = s.al * std::exp(T(-0.5) * dl * dl);
                c[i] += T(-0.25) * Gt / (T(1) - Gt) * std::fabs(dl) * isg;
            });
            for (int i = 0; i < TP; ++i) c[i] = gt[i] / std::max(-c[i], T(1e-7));
            pairs += for_pairs<T>(A, tile, maxlast, P, BND, [&](int i, int kk, int g, const T* p, T px, T py) {
                if (gt[i] == T(0)) return;
                const SolidPair<T> s = solid_pair<T>(p, px, py, kk, lastk[i]);
                if (!s.v) return;
                const T isg = ISG[g], dt = tm[i] - s.tpk, dl = dt * isg;
                const T Ge = std::exp(T(-0.5) * dl * dl), Gt = s.al * Ge;
                T dGt = c[i] * T(0.25) / (T(1) - Gt);
                dGt = tm[i] > s.tpk ? dGt : -dGt;
                dGt = isg > T(0) ? dGt : T(0);
                const T dal = dGt * Ge - (dl > T(0) ? c[i] * T(0.5) / (T(1) - s.al) : T(0));
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
            });
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
