// gsbench tile rasterizer: the exact ellipse/tile overlap binning of ewa and rade.

#include "raster_common.h"

// ---------------------------------------------------------------------------------------------
// Exact ellipse/tile overlap binning (ewa, rade).
//
// A pixel (centre p, d = p − mean2d) gets a contribution from an ewa/rade Gaussian only if
// o·exp(−q/2) >= 1/255 with q = A dx² + 2B dx dy + C dy² (the conic of the payload), i.e. q <= K with
// K = 2 ln(255 o) (+ slack for fexp, the rounding of o·G and of 1/255). The compositor evaluates q in T
// (float32 or float64): its value is >= q − ε S(d), S(d) = |A|dx² + 2|B||dx dy| + |C|dy², so the pixel
// lies in the ellipse dᵀQ'd <= K with Q' = Q − ε diag(|A| + |B|, |C| + |B|) (ε = a generous bound of the
// evaluation's relative error). A Gaussian is listed in a tile iff that ellipse meets the rectangle of
// the tile's pixel centres (and the tile lies in its `rect`, as before): per tile row, the x-range of the
// ellipse over the row's band of pixel-centre ys gives a contiguous range of tile columns. Everything
// here is double precision with outward padding, so the test is conservative: a dropped tile has no
// pixel whose contribution is non-zero, and the images and gradients are bit-identical to the rectangle
// binning (tile lists keep depth order). Degenerate conics (Q' not positive definite, or far too
// elongated) and huge opacities fall back to the rectangle.
//
// The distortion output shifts depths by the first Gaussian of each tile list (m0), so with
// ``keep_first`` each tile also keeps the first (front-most) Gaussian whose rectangle covers it.
// ---------------------------------------------------------------------------------------------

namespace {

constexpr int ELL_N = 10;  // per entry: mode, mx, my, b, aK, det, 1/a, hy (padded), ys, pad
constexpr double ELL_RECT = 0.0, ELL_EMPTY = 1.0, ELL_CONIC = 2.0;

// ln x for finite x >= 0.5 (no libm call): x = 2^e m, m in [√½, √2), ln m = 2 atanh(s), s = (m − 1)/(m + 1),
// |s| <= 0.172; the series to s⁹ is within 1e-9 (the caller's slack is 1e-3)
inline double ln_pos(double x) {
    const uint64_t bits = __builtin_bit_cast(uint64_t, x);
    int e = (int)((bits >> 52) & 0x7ff) - 1022;
    double m = __builtin_bit_cast(double, (bits & 0x000fffffffffffffull) | (1022ull << 52));  // [0.5, 1)
    if (m < 0.70710678118654752) {
        m *= 2.0;
        e -= 1;
    }
    const double s = (m - 1.0) / (m + 1.0), s2 = s * s;
    const double p = s * (2.0 + s2 * (2.0 / 3.0 + s2 * (2.0 / 5.0 + s2 * (2.0 / 7.0 + s2 * (2.0 / 9.0)))));
    return (double)e * 0.69314718055994531 + p;
}

template <typename T>
inline void make_ellipse(const T* p, double* e) {
    const double A = (double)p[P_CA], B = (double)p[P_CB], C = (double)p[P_CC], o = (double)p[P_O];
    const double eps = sizeof(T) == 4 ? 1e-5 : 1e-12;
    const double mx = (double)p[P_MX], my = (double)p[P_MY];
    e[1] = mx;
    e[2] = my;
    if (!(o * 255.0 > 0.5)) {  // o·G <= o < 1/255 (with a wide margin below 1/255): never contributes
        e[0] = ELL_EMPTY;
        return;
    }
    const double tau2 = 2.0 * ln_pos(255.0 * o);
    const double K = tau2 + 1e-3 + 1e-4 * std::fabs(tau2);
    if (K < 0.0) {
        e[0] = ELL_EMPTY;
        return;
    }
    const double mag = std::fabs(A) + std::fabs(B) + std::fabs(C);
    // G is clamped at exp(−30): at K ~ 60 every pixel may pass; huge entries: keep the rectangle
    if (K > 50.0 || !(mag < 1e150) || !(std::fabs(mx) < 1e12) || !(std::fabs(my) < 1e12)) {
        e[0] = ELL_RECT;
        return;
    }
    const double a = A - eps * (std::fabs(A) + std::fabs(B));
    const double c = C - eps * (std::fabs(C) + std::fabs(B));
    const double det = a * c - B * B;
    if (!(a > 0.0) || !(c > 0.0) || !(det > 1e-12 * a * c)) {
        e[0] = ELL_RECT;
        return;
    }
    const double hx = std::sqrt(K * c / det);  // half extent in x
    const double hy = std::sqrt(K * a / det) * (1.0 + 1e-9) + 1e-6;  // half extent in y, padded
    const double inv_a = 1.0 / a;
    e[0] = ELL_CONIC;
    e[3] = B;
    e[4] = a * K;
    e[5] = det;
    e[6] = inv_a;
    e[7] = hy;
    e[8] = -B * hx / c;  // dy of the rightmost point (the leftmost is at −ys)
    e[9] = 1e-6 * (hx + std::fabs(B) * inv_a * hy + std::fabs(mx)) + 1e-3;  // outward x padding (rounding)
}

// Tile columns [c0, c1) (within [r0, r1)) whose pixel-centre rectangle meets the conic ellipse e in tile row ty;
// branch-free, so `ellipse_records` runs it as SIMD lanes.
inline void conic_row_span(const double* e, int ty, int H, double r0, double r1, int& c0, int& c1) {
    const double mx = e[1], my = e[2], b = e[3], aK = e[4], det = e[5], inv_a = e[6], hy = e[7], ys = e[8],
                 pad = e[9];
    const int yy0 = ty * TS;
    const int nrows = std::min(TS, H - yy0);
    const double lo = std::max((double)yy0 + 0.5 - my, -hy);
    const double hi = std::min((double)(yy0 + nrows) - 0.5 - my, hy);
    // right edge R(dy) = (−b dy + √(aK − det dy²))/a is concave, maximal at dy = ys; the left edge mirrors it
    const double dyr = std::min(std::max(ys, lo), hi);
    const double dyl = std::min(std::max(-ys, lo), hi);
    const double xr = mx + (-b * dyr + std::sqrt(std::max(0.0, aK - det * dyr * dyr))) * inv_a;
    const double xl = mx + (-b * dyl - std::sqrt(std::max(0.0, aK - det * dyl * dyl))) * inv_a;
    // tile tx's pixel centres span x in [16 tx + 0.5, 16 tx + 15.5]
    const double flo = std::ceil(((xl - pad) - (TS - 0.5)) * (1.0 / TS));
    const double fhi = std::floor(((xr + pad) - 0.5) * (1.0 / TS)) + 1.0;
    const double d0 = std::min(std::max(flo, r0), r1);
    const double d1 = std::max(std::min(std::max(fhi, r0), r1), d0);
    const bool empty = lo > hi;
    c0 = empty ? (int)r0 : (int)d0;
    c1 = empty ? (int)r0 : (int)d1;
}

// Tile columns [c0, c1) of tile row ty for any ellipse record: the whole rectangle row, none, or the conic's span.
inline void ellipse_row_span(const double* e, int ty, int H, int r0, int r1, int& c0, int& c1) {
    if (e[0] == ELL_RECT) {
        c0 = r0;
        c1 = r1;
    } else if (e[0] != ELL_CONIC) {
        c0 = c1 = r0;
    } else {
        conic_row_span(e, ty, H, r0, r1, c0, c1);
    }
}

// first[t] = the first entry (depth order) whose rectangle covers tile t, -1 if none.
inline void first_cover(int64_t M, const int32_t* rs, int64_t tiles_x, int64_t tiles_y, int32_t* first) {
    const int64_t ntiles = tiles_x * tiles_y;
    for (int64_t t = 0; t < ntiles; ++t) first[t] = -1;
    int64_t left = ntiles;
    for (int64_t j = 0; j < M && left > 0; ++j) {
        const int32_t* r = rs + 4 * j;
        for (int y = r[2]; y < r[3]; ++y)
            for (int x = r[0]; x < r[1]; ++x) {
                int32_t& f = first[y * tiles_x + x];
                if (f < 0) {
                    f = (int32_t)j;
                    --left;
                }
            }
    }
}

// Per-Gaussian record (REC int32, in id order, computed in one sequential pass): rec[0] = mode; REC_SPANS: the
// tile-column range of each rectangle row, c0 | c1 << 16, in rec[1 ..]; REC_RECOMPUTE (more rows than fit):
// the count and fill passes rebuild the ellipse from the payload (same code, same result).
constexpr int REC = 8, REC_ROWS = REC - 1;
constexpr int32_t REC_RECT = 0, REC_EMPTY = 1, REC_SPANS = 2, REC_RECOMPUTE = 3;

template <typename T>
void ellipse_records(int64_t N, const uint8_t* visible, const int32_t* rect, const T* P, int64_t npar, int64_t H,
                     int64_t tiles_x, int32_t* rec, int nt) {
#pragma omp parallel for num_threads(nt) schedule(static, 1024)
    for (int64_t i = 0; i < N; ++i) {
        int32_t* q = rec + REC * i;
        const int32_t* r = rect + 4 * i;
        if (!visible[i] || (r[1] - r[0]) * (r[3] - r[2]) <= 1 || tiles_x >= 32768) {  // one tile: nothing to gain
            q[0] = REC_RECT;
            continue;
        }
        double e[ELL_N];
        make_ellipse<T>(P + i * npar, e);
        if (e[0] == ELL_RECT) {
            q[0] = REC_RECT;
        } else if (e[0] == ELL_EMPTY) {
            q[0] = REC_EMPTY;
        } else if (r[3] - r[2] > REC_ROWS) {
            q[0] = REC_RECOMPUTE;
        } else {
            // conic_row_span of the (at most REC_ROWS) rows as SIMD lanes
            q[0] = REC_SPANS;
            const int ty0 = r[2], nr = r[3] - r[2];
            int32_t out[8];
#pragma omp simd
            for (int k = 0; k < 8; ++k) {
                int c0, c1;
                conic_row_span(e, ty0 + k, (int)H, r[0], r[1], c0, c1);
                out[k] = c0 | (c1 << 16);
            }
            for (int k = 0; k < nr; ++k) q[1 + k] = out[k];
        }
    }
}

// Calls f(y, c0, c1) for every rectangle row y of entry (g, r) with its tile-column range.
template <typename T, class F>
inline void for_row_spans(const int32_t* q, const int32_t* r, const T* P, int64_t npar, int H, int32_t g, F&& f) {
    switch (q[0]) {
        case REC_SPANS:
            for (int y = r[2]; y < r[3]; ++y) {
                const int32_t v = q[1 + y - r[2]];
                f(y, v & 0xffff, v >> 16);
            }
            break;
        case REC_EMPTY:
            for (int y = r[2]; y < r[3]; ++y) f(y, r[0], r[0]);
            break;
        case REC_RECOMPUTE: {
            double e[ELL_N];
            make_ellipse<T>(P + (int64_t)g * npar, e);
            for (int y = r[2]; y < r[3]; ++y) {
                int c0, c1;
                ellipse_row_span(e, y, H, r[0], r[1], c0, c1);
                f(y, c0, c1);
            }
            break;
        }
        default:
            for (int y = r[2]; y < r[3]; ++y) f(y, r[0], r[1]);
    }
}

// Entries [M k / nt, M (k + 1) / nt) form chunk k; the count pass counts each chunk's pairs per tile and
// leaves in `cursors` (nt × tiles) where chunk k starts writing in each tile, so the fill pass writes every
// chunk independently and each tile list stays in depth order.
template <typename T>
int64_t bin_exact_count_impl(int64_t M, const int32_t* order, const int32_t* rs, int64_t N, const uint8_t* visible,
                             const int32_t* rect, const T* P, int64_t npar, int64_t H, int64_t tiles_x,
                             int64_t tiles_y, int32_t* first, int32_t* rec, int32_t* offsets, int32_t* cursors,
                             int64_t nchunks) {
    const int64_t ntiles = tiles_x * tiles_y;
    const int nt = (int)std::max<int64_t>(1, nchunks);
    ellipse_records<T>(N, visible, rect, P, npar, H, tiles_x, rec, nt);
    if (first) first_cover(M, rs, tiles_x, tiles_y, first);
    std::fill(cursors, cursors + (int64_t)nt * ntiles, 0);
#pragma omp parallel for num_threads(nt) schedule(static, 1)
    for (int k = 0; k < nt; ++k) {
        int32_t* cnt = cursors + (int64_t)k * ntiles;
        const int64_t jb = M * k / nt, je = M * (k + 1) / nt;
        for (int64_t j = jb; j < je; ++j) {
            if (j + 32 < je) __builtin_prefetch(rec + REC * (int64_t)order[j + 32], 0, 1);
            const int32_t g = order[j];
            const int32_t* r = rs + 4 * j;
            for_row_spans<T>(rec + REC * (int64_t)g, r, P, npar, (int)H, g, [&](int y, int c0, int c1) {
                int32_t* cr = cnt + y * tiles_x;
                for (int x = c0; x < c1; ++x) cr[x]++;
                if (first) {
                    const int32_t* fr = first + y * tiles_x;
                    for (int x = r[0]; x < c0; ++x) cr[x] += fr[x] == (int32_t)j;
                    for (int x = c1; x < r[1]; ++x) cr[x] += fr[x] == (int32_t)j;
                }
            });
        }
    }
    int64_t run = 0;
    offsets[0] = 0;
    for (int64_t t = 0; t < ntiles; ++t) {
        for (int k = 0; k < nt; ++k) {  // counts -> start positions
            const int32_t c = cursors[(int64_t)k * ntiles + t];
            cursors[(int64_t)k * ntiles + t] = (int32_t)run;
            run += c;
            if (run > INT32_MAX) return -1;
        }
        offsets[t + 1] = (int32_t)run;
    }
    return run;
}

template <typename T>
int64_t bin_exact_fill_impl(int64_t M, const int32_t* order, const int32_t* rs, const int32_t* rec, const T* P,
                            int64_t npar, int64_t H, int64_t tiles_x, int64_t tiles_y, const int32_t* first,
                            const int32_t* offsets, int32_t* cursors, int32_t* list, int64_t capacity,
                            int64_t nchunks) {
    const int64_t ntiles = tiles_x * tiles_y;
    const int nt = (int)std::max<int64_t>(1, nchunks);
    if (offsets[ntiles] > capacity) return -1;
#pragma omp parallel for num_threads(nt) schedule(static, 1)
    for (int k = 0; k < nt; ++k) {
        int32_t* cur = cursors + (int64_t)k * ntiles;
        const int64_t jb = M * k / nt, je = M * (k + 1) / nt;
        for (int64_t j = jb; j < je; ++j) {
            if (j + 32 < je) __builtin_prefetch(rec + REC * (int64_t)order[j + 32], 0, 1);
            const int32_t* r = rs + 4 * j;
            const int32_t g = order[j];
            for_row_spans<T>(rec + REC * (int64_t)g, r, P, npar, (int)H, g, [&](int y, int c0, int c1) {
                int32_t* c = cur + y * tiles_x;
                for (int x = c0; x < c1; ++x) list[c[x]++] = g;
                if (first) {
                    const int32_t* fr = first + y * tiles_x;
                    for (int x = r[0]; x < c0; ++x)
                        if (fr[x] == (int32_t)j) list[c[x]++] = g;
                    for (int x = c1; x < r[1]; ++x)
                        if (fr[x] == (int32_t)j) list[c[x]++] = g;
                }
            });
        }
    }
    return offsets[ntiles];
}

}  // namespace

extern "C" {

// Count pass of the exact ellipse/tile binning of ewa/rade on the output of gs_depth_order (M, order, rs):
// `visible` (N,) and `rect` (N, 4) as given to gs_depth_order, `params` the payload (N, n_params), dtype
// 0 = float32, 1 = float64, `nchunks` the number of chunks (= threads) of both passes. Fills `rec` (N × 8
// int32), `cursors` (nchunks × tiles int32), both read by gs_bin_exact_fill, `first` (tiles int32, only when
// keep_first; may be null otherwise) and `offsets` (tiles + 1). Returns the pair count (the exact
// capacity), -1 on overflow.
int64_t gs_bin_exact_count(int64_t M, const int32_t* order, const int32_t* rs, int64_t N, const uint8_t* visible,
                           const int32_t* rect, const void* params, int64_t n_params, int64_t dtype, int64_t height,
                           int64_t tiles_x, int64_t tiles_y, int64_t keep_first, int32_t* first, int32_t* rec,
                           int32_t* offsets, int32_t* cursors, int64_t nchunks) {
    int32_t* f = keep_first ? first : nullptr;
    return dtype == 0 ? bin_exact_count_impl<float>(M, order, rs, N, visible, rect, (const float*)params, n_params,
                                                    height, tiles_x, tiles_y, f, rec, offsets, cursors, nchunks)
                      : bin_exact_count_impl<double>(M, order, rs, N, visible, rect, (const double*)params, n_params,
                                                     height, tiles_x, tiles_y, f, rec, offsets, cursors, nchunks);
}

// Fill pass: the per-tile lists (depth order) into `list` (same arguments as the count pass; `cursors` is
// consumed). Returns the pair count, or -1 if it exceeds `capacity`.
int64_t gs_bin_exact_fill(int64_t M, const int32_t* order, const int32_t* rs, const int32_t* rec, const void* params,
                          int64_t n_params, int64_t dtype, int64_t height, int64_t tiles_x, int64_t tiles_y,
                          int64_t keep_first, const int32_t* first, const int32_t* offsets, int32_t* cursors,
                          int32_t* list, int64_t capacity, int64_t nchunks) {
    const int32_t* f = keep_first ? first : nullptr;
    return dtype == 0 ? bin_exact_fill_impl<float>(M, order, rs, rec, (const float*)params, n_params, height, tiles_x,
                                                   tiles_y, f, offsets, cursors, list, capacity, nchunks)
                      : bin_exact_fill_impl<double>(M, order, rs, rec, (const double*)params, n_params, height,
                                                    tiles_x, tiles_y, f, offsets, cursors, list, capacity, nchunks);
}

}  // extern "C"
