// gsbench tile rasterizer: the exact ellipse/tile overlap binning of ewa, rade and surfel.

#include "raster_common.h"

// ---------------------------------------------------------------------------------------------
// Exact ellipse/tile overlap binning (ewa, rade; surfels through make_surfel_ellipse below).
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

// K, padded for fexp, the rounding of o·G and of 1/255, such that a pixel contributes (o·exp(−q/2) >= 1/255) only
// where q <= K = 2 ln(255 o); negative when nothing can contribute (o below 1/255, with a wide margin).
inline double alpha_bound(double o) {
    if (!(o * 255.0 > 0.5)) return -1.0;
    const double tau2 = 2.0 * ln_pos(255.0 * o);
    return tau2 + 1e-3 + 1e-4 * std::fabs(tau2);
}

template <typename T>
inline void make_ellipse(const T* p, double* e) {
    const double A = (double)p[P_CA], B = (double)p[P_CB], C = (double)p[P_CC], o = (double)p[P_O];
    const double eps = sizeof(T) == 4 ? 1e-5 : 1e-12;
    const double mx = (double)p[P_MX], my = (double)p[P_MY];
    e[1] = mx;
    e[2] = my;
    const double K = alpha_bound(o);
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

// What the records need beyond the payload (gs_bin_exact_count's `setup`): the kernel (0: ewa/rade, 1: surfel)
// and, for surfels, the camera's fx, fy, cx, cy and the low-pass k.
struct BinSetup {
    double surfel, fx, fy, cx, cy, surfel_k;
};

// A Gaussian's contributing set as up to two padded ellipses (the second ELL_EMPTY when unused); the tile
// spans of a row are the hull of theirs.
struct Shape {
    double e[2][ELL_N];
};

// The surfel's 3D branch (docs/methods/2dgs.md §3.2): with r = (rx, ry, 1) = ((x − cx)/fx, (y − cy)/fy, 1) the
// pixel's ray, ρ = s_u² + s_v², s_u = (d a_u·r − b_u n·r)/(n·r), so ρ <= K is (U·r)² + (V·r)² − K (n·r)² <= 0 with
// U = d a_u − b_u n, V = d a_v − b_v n: a conic in (rx, ry), A rx² + 2B rx ry + C ry² + 2D rx + 2E ry + F <= 0
// (both sheets of the cone: a superset). Where it is an ellipse it is written in make_ellipse's form about its
// centre r0 = −M⁻¹(D, E) (in pixels: M scaled by fx, fy), with K_c = −Q(r0) (Q evaluated at r0, which is
// insensitive to r0's rounding to first order; F + (D, E)·r0 is not) widened by Q's rounding and by the
// centre's; a hyperbola or parabola (grazing or crossing splats) keeps the rectangle. K = 2 ln(255 o) padded as
// make_ellipse pads it, then √K widened by 128 ε (|b_u| + |b_v| + |d| Σ|a| + 4) for the float lanes' rounding
// of s_u, s_v (ε of T). Working in rays, not pixel offsets from the projected centre, keeps the coefficients
// small when that centre is far away (a splat near the camera plane).
template <typename T>
inline void make_surfel_ellipse(const T* p, const BinSetup& s, double* e) {
    e[0] = ELL_RECT;
    const double K0 = alpha_bound((double)p[P_O]);
    if (K0 < 0.0) {
        e[0] = ELL_EMPTY;
        return;
    }
    const T* X = p + P_X;  // n (3), d, a_u (3), b_u, a_v (3), b_v
    const double d = (double)X[3], bu = (double)X[7], bv = (double)X[11];
    double n[3], U[3], V[3], amag = 0.0;
    for (int j = 0; j < 3; ++j) {
        n[j] = (double)X[j];
        U[j] = d * (double)X[4 + j] - bu * n[j];
        V[j] = d * (double)X[8 + j] - bv * n[j];
        amag += std::fabs((double)X[4 + j]) + std::fabs((double)X[8 + j]);
    }
    const double eps = sizeof(T) == 4 ? 6e-8 : 1.2e-16;
    const double ds = 64.0 * eps * (std::fabs(bu) + std::fabs(bv) + std::fabs(d) * amag + 4.0);
    const double K = (std::sqrt(K0) + 2.0 * ds) * (std::sqrt(K0) + 2.0 * ds);
    const double mag = std::fabs(d) + std::fabs(bu) + std::fabs(bv) + amag;
    if (K > 50.0 || !(mag < 1e12)) return;
    const double A = U[0] * U[0] + V[0] * V[0] - K * n[0] * n[0];
    const double B = U[0] * U[1] + V[0] * V[1] - K * n[0] * n[1];
    const double C = U[1] * U[1] + V[1] * V[1] - K * n[1] * n[1];
    const double D = U[0] * U[2] + V[0] * V[2] - K * n[0] * n[2];
    const double E = U[1] * U[2] + V[1] * V[2] - K * n[1] * n[2];
    const double F = U[2] * U[2] + V[2] * V[2] - K * n[2] * n[2];
    const double det = A * C - B * B;
    if (!(A > 0.0) || !(C > 0.0) || !(det > 1e-9 * A * C)) return;
    constexpr double E64 = 1.2e-16;
    const double rx0 = -(C * D - B * E) / det, ry0 = -(A * E - B * D) / det;
    const double ex = 16.0 * E64 * (std::fabs(C * D) + std::fabs(B * E)) / det + 16.0 * E64 * std::fabs(rx0);
    const double ey = 16.0 * E64 * (std::fabs(A * E) + std::fabs(B * D)) / det + 16.0 * E64 * std::fabs(ry0);
    const double t1 = A * rx0 * rx0, t2 = 2.0 * B * rx0 * ry0, t3 = C * ry0 * ry0, t4 = 2.0 * D * rx0,
                 t5 = 2.0 * E * ry0;
    const double q0 = t1 + t2 + t3 + t4 + t5 + F;
    const double qerr = 64.0 * E64 * (std::fabs(t1) + std::fabs(t2) + std::fabs(t3) + std::fabs(t4) + std::fabs(t5) +
                                      std::fabs(F));
    const double shift = A * ex * ex + 2.0 * std::fabs(B) * ex * ey + C * ey * ey;  // (centre error)ᵀ M (…)
    const double kin = -q0 + qerr;
    if (kin < 0.0) {
        e[0] = ELL_EMPTY;
        return;
    }
    const double Kc = (std::sqrt(kin) + 2.0 * std::sqrt(shift)) * (std::sqrt(kin) + 2.0 * std::sqrt(shift));
    // in pixels: x = cx + fx rx, so the pixel conic is M scaled by 1/fx, 1/fy with the same K_c
    const double a = A / (s.fx * s.fx), b = B / (s.fx * s.fy), c = C / (s.fy * s.fy), dp = det / (s.fx * s.fx * s.fy * s.fy);
    const double cxp = s.cx + s.fx * rx0, cyp = s.cy + s.fy * ry0;
    if (!(std::fabs(cxp) < 1e9) || !(std::fabs(cyp) < 1e9)) return;
    const double hx = std::sqrt(Kc * c / dp);
    const double hy = std::sqrt(Kc * a / dp) * (1.0 + 1e-6) + 1e-3;
    e[0] = ELL_CONIC;
    e[1] = cxp;
    e[2] = cyp;
    e[3] = b;
    e[4] = a * Kc;
    e[5] = dp;
    e[6] = 1.0 / a;
    e[7] = hy;
    e[8] = -b * hx / c;
    e[9] = 1e-6 * (hx + std::fabs(b) * e[6] * hy + std::fabs(cxp)) + 1e-3;
}

template <typename T>
inline void make_shape(const T* p, const BinSetup& s, Shape& sh) {
    sh.e[1][0] = ELL_EMPTY;
    if (s.surfel == 0.0) {
        make_ellipse<T>(p, sh.e[0]);
        return;
    }
    make_surfel_ellipse<T>(p, s, sh.e[0]);
    if (s.surfel_k > 0.0) {  // the low-pass branch ρ = k |centre − pixel|²: the disc as make_ellipse's conic k I
        T q[P_X] = {p[P_MX], p[P_MY], (T)s.surfel_k, T(0), (T)s.surfel_k, p[P_O]};
        make_ellipse<T>(q, sh.e[1]);
    }
}

inline double shape_mode(const Shape& sh) {
    const double m0 = sh.e[0][0], m1 = sh.e[1][0];
    if (m0 == ELL_RECT || m1 == ELL_RECT) return ELL_RECT;
    return (m0 == ELL_EMPTY && m1 == ELL_EMPTY) ? ELL_EMPTY : ELL_CONIC;
}

// Tile columns [c0, c1) of tile row ty (within [r0, r1)): the hull of the shape's ellipses' spans.
inline void shape_row_span(const Shape& sh, int ty, int H, int r0, int r1, int& c0, int& c1) {
    c0 = c1 = r0;
    for (int k = 0; k < 2; ++k) {
        int a0, a1;
        ellipse_row_span(sh.e[k], ty, H, r0, r1, a0, a1);
        if (a0 >= a1) continue;
        if (c0 >= c1) {
            c0 = a0;
            c1 = a1;
        } else {
            c0 = std::min(c0, a0);
            c1 = std::max(c1, a1);
        }
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
                     int64_t tiles_x, const BinSetup& setup, int32_t* rec, int nt) {
#pragma omp parallel for num_threads(nt) schedule(static, 1024)
    for (int64_t i = 0; i < N; ++i) {
        int32_t* q = rec + REC * i;
        const int32_t* r = rect + 4 * i;
        if (!visible[i] || (r[1] - r[0]) * (r[3] - r[2]) <= 1 || tiles_x >= 32768) {  // one tile: nothing to gain
            q[0] = REC_RECT;
            continue;
        }
        Shape sh;
        make_shape<T>(P + i * npar, setup, sh);
        const double mode = shape_mode(sh);
        if (mode == ELL_RECT) {
            q[0] = REC_RECT;
        } else if (mode == ELL_EMPTY) {
            q[0] = REC_EMPTY;
        } else if (r[3] - r[2] > REC_ROWS) {
            q[0] = REC_RECOMPUTE;
        } else {
            q[0] = REC_SPANS;
            const int ty0 = r[2], nr = r[3] - r[2];
            int32_t out[8];
            if (sh.e[1][0] == ELL_EMPTY && sh.e[0][0] == ELL_CONIC) {  // one ellipse: conic_row_span as SIMD lanes
                const double* e = sh.e[0];
#pragma omp simd
                for (int k = 0; k < 8; ++k) {
                    int c0, c1;
                    conic_row_span(e, ty0 + k, (int)H, r[0], r[1], c0, c1);
                    out[k] = c0 | (c1 << 16);
                }
            } else {
                for (int k = 0; k < nr; ++k) {
                    int c0, c1;
                    shape_row_span(sh, ty0 + k, (int)H, r[0], r[1], c0, c1);
                    out[k] = c0 | (c1 << 16);
                }
            }
            for (int k = 0; k < nr; ++k) q[1 + k] = out[k];
        }
    }
}

// Calls f(y, c0, c1) for every rectangle row y of entry (g, r) with its tile-column range.
template <typename T, class F>
inline void for_row_spans(const int32_t* q, const int32_t* r, const T* P, int64_t npar, int H, int32_t g,
                          const BinSetup& setup, F&& f) {
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
            Shape sh;
            make_shape<T>(P + (int64_t)g * npar, setup, sh);
            for (int y = r[2]; y < r[3]; ++y) {
                int c0, c1;
                shape_row_span(sh, y, H, r[0], r[1], c0, c1);
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
                             int64_t nchunks, const BinSetup& setup) {
    const int64_t ntiles = tiles_x * tiles_y;
    const int nt = (int)std::max<int64_t>(1, nchunks);
    ellipse_records<T>(N, visible, rect, P, npar, H, tiles_x, setup, rec, nt);
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
            for_row_spans<T>(rec + REC * (int64_t)g, r, P, npar, (int)H, g, setup, [&](int y, int c0, int c1) {
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
                            int64_t nchunks, const BinSetup& setup) {
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
            for_row_spans<T>(rec + REC * (int64_t)g, r, P, npar, (int)H, g, setup, [&](int y, int c0, int c1) {
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

// Count pass of the exact ellipse/tile binning of ewa/rade/surfel on the output of gs_depth_order (M, order, rs):
// `visible` (N,) and `rect` (N, 4) as given to gs_depth_order, `params` the payload (N, n_params), dtype
// 0 = float32, 1 = float64, `nchunks` the number of chunks (= threads) of both passes, `setup` the six
// doubles of BinSetup (surfel flag, fx, fy, cx, cy, low-pass k). Fills `rec` (N × 8
// int32), `cursors` (nchunks × tiles int32), both read by gs_bin_exact_fill, `first` (tiles int32, only when
// keep_first; may be null otherwise) and `offsets` (tiles + 1). Returns the pair count (the exact
// capacity), -1 on overflow.
int64_t gs_bin_exact_count(int64_t M, const int32_t* order, const int32_t* rs, int64_t N, const uint8_t* visible,
                           const int32_t* rect, const void* params, int64_t n_params, int64_t dtype, int64_t height,
                           int64_t tiles_x, int64_t tiles_y, int64_t keep_first, int32_t* first, int32_t* rec,
                           int32_t* offsets, int32_t* cursors, int64_t nchunks, const double* setup) {
    int32_t* f = keep_first ? first : nullptr;
    const BinSetup s{setup[0], setup[1], setup[2], setup[3], setup[4], setup[5]};
    return dtype == 0 ? bin_exact_count_impl<float>(M, order, rs, N, visible, rect, (const float*)params, n_params,
                                                    height, tiles_x, tiles_y, f, rec, offsets, cursors, nchunks, s)
                      : bin_exact_count_impl<double>(M, order, rs, N, visible, rect, (const double*)params, n_params,
                                                     height, tiles_x, tiles_y, f, rec, offsets, cursors, nchunks, s);
}

// Fill pass: the per-tile lists (depth order) into `list` (same arguments as the count pass; `cursors` is
// consumed). Returns the pair count, or -1 if it exceeds `capacity`.
int64_t gs_bin_exact_fill(int64_t M, const int32_t* order, const int32_t* rs, const int32_t* rec, const void* params,
                          int64_t n_params, int64_t dtype, int64_t height, int64_t tiles_x, int64_t tiles_y,
                          int64_t keep_first, const int32_t* first, const int32_t* offsets, int32_t* cursors,
                          int32_t* list, int64_t capacity, int64_t nchunks, const double* setup) {
    const int32_t* f = keep_first ? first : nullptr;
    const BinSetup s{setup[0], setup[1], setup[2], setup[3], setup[4], setup[5]};
    return dtype == 0 ? bin_exact_fill_impl<float>(M, order, rs, rec, (const float*)params, n_params, height, tiles_x,
                                                   tiles_y, f, offsets, cursors, list, capacity, nchunks, s)
                      : bin_exact_fill_impl<double>(M, order, rs, rec, (const double*)params, n_params, height,
                                                    tiles_x, tiles_y, f, offsets, cursors, list, capacity, nchunks, s);
}

}  // extern "C"
