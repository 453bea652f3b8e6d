// Fused SSIM map and its backward (the D-SSIM loss term) for float32 and float64 images; Python API and
// the PyTorch reference: gsbench/losses/ssim.py; tests: tests/test_ssim_fused.py. Plain C ABI, OpenMP over bands
// of image rows.
//
// Layout: x, y, map, g_map, g_x are (H, W, C) C-contiguous, so an image row is W·C contiguous values with
// the channels interleaved; coef is (3, H, W, C) in the same dtype. g1d is the normalised 1-D Gaussian,
// 11 taps (radius R = 5), float64. All arithmetic is in float64 whatever the storage type T (float32 images
// are converted row by row on load and rounded once on store), so the float32 path returns the float64
// result rounded to float32 (the PyTorch reference in float32 loses up to ~1e-3 to cancellation in
// E[x²] − μx² on smooth images; see tests/test_ssim_fused.py).
//
// Blur. The reference (gsbench/losses/ssim.py, `ssim_map_reference`) is a grouped conv2d with the 11×11 window
// outer(g, g) and zero padding 5 ('same' output). That window is separable, so the blur is a horizontal
// 11-tap pass over W followed by a vertical 11-tap pass over H, each 'same' with zero padding:
//   h[i, j] = Σ_k g[k] s[i, j + k − R],   b[i, j] = Σ_k g[k] h[i + k − R, j],
// where values outside the image are 0, exactly as in the zero-padded 2-D convolution. Here a row is
// copied into a buffer with R·C zeros on each side (so tap k of element e = j·C + c reads e + k·C of the
// buffer, the same channel), and rows outside [0, H) are rows of zeros.
//
// Forward, per pixel and channel: the horizontal pass blurs x, y, x², y², xy (products formed on the fly)
// and the vertical pass gives μx, μy, E[x²], E[y²], E[xy]; then
//   σx² = E[x²] − μx², σy² = E[y²] − μy², σxy = E[xy] − μx μy,
//   A1 = 2 μx μy + C1, A2 = 2 σxy + C2, B1 = μx² + μy² + C1, B2 = σx² + σy² + C2,   S = A1 A2 / (B1 B2),
// with B1, B2 evaluated as A1 + (μx − μy)² and A2 + (E[x²] + E[y²] − 2E[xy]) − (μx − μy)² (equal in exact
// arithmetic; identical images then give S = 1 exactly, as in the reference).
// With coef != NULL it also stores the three partials of S with respect to the blurred moments of x
// that the backward needs (μy, E[y²] belong to y, which gets no gradient):
//   ∂S/∂μx    = 2 μy (A2 − A1) / (B1 B2) + 2 μx S (1/B2 − 1/B1)    (A1: +2μy; A2: −2μy via σxy;
//                                                                 B1: +2μx; B2: −2μx via σx²)
//   ∂S/∂E[x²] = −S / B2                                          (via σx² only)
//   ∂S/∂E[xy] = 2 A1 / (B1 B2)                                   (via σxy only)
//
// Backward: given G = dL/dS (H, W, C), dL/dm = G · ∂S/∂m per pixel for each moment m. The moments are blurs
// of functions of x: μx = B(x), E[x²] = B(x²), E[xy] = B(x·y), with B the linear blur. B's matrix is
// symmetric (each 1-D 'same' zero-padded pass with a symmetric kernel has matrix M[j, j'] = g[j' − j + R]
// = g[j − j' + R], and the 2-D blur is the product of the horizontal and the vertical pass, which act on
// different axes and commute), so Bᵀ = B and
//   dL/dx = B(G ∂S/∂μx) + 2x · B(G ∂S/∂E[x²]) + y · B(G ∂S/∂E[xy]).
// The backward forms the three products row by row, blurs them with the same two passes and combines.
//
// Parallel structure: the rows are split into one band per thread. A thread keeps a ring of the 11
// horizontally blurred rows its current output row needs (NQ quantities each) and slides it down its
// band: one new horizontal row and one vertical sum per output row. Memory per thread: 11·NQ + 2..3 rows of
// W·C doubles (no full-image scratch); the cost of the bands is R rows of horizontal work recomputed on each
// side of a band boundary.
#include <algorithm>
#include <cstdint>
#include <cstring>
#include <omp.h>
#include <vector>

namespace {

constexpr int R = 5;           // window radius
constexpr int K = 2 * R + 1;   // taps
constexpr int L = 4;           // doubles per vector
constexpr int V = 2 * L;       // elements per chunk (two vectors per quantity, registers only)
// Images with fewer values than this run on the calling thread (a parallel region costs more than they do).
constexpr int64_t MIN_PARALLEL = 8192;
// At least this many output rows per band (the halo of a band is 2R rows of horizontal work).
constexpr int64_t MIN_BAND_ROWS = 16;

typedef double vd __attribute__((vector_size(L * sizeof(double))));
typedef float vf __attribute__((vector_size(L * sizeof(float))));

inline vd load(const double* p) {
    vd v;
    std::memcpy(&v, p, sizeof(vd));
    return v;
}

inline void store(double* p, vd v) { std::memcpy(p, &v, sizeof(vd)); }

inline vd splat(double s) { return vd{} + s; }

// Store L results in T (float32 results rounded once).
inline void store_out(float* p, vd v) {
    const vf f = __builtin_convertvector(v, vf);
    std::memcpy(p, &f, sizeof(vf));
}

inline void store_out(double* p, vd v) { store(p, v); }

template <class T>
inline vd load_in(const T* p) {
    double tmp[L];
    for (int l = 0; l < L; ++l) tmp[l] = double(p[l]);
    return load(tmp);
}

// Per-thread buffers: padded input rows (NIN of them, R·C zeros on each side, rounded up to whole chunks)
// and the ring of the last K horizontally blurred rows, NQ quantities each, row stride WCp.
struct Work {
    int64_t WCp, C, pad;
    int nq;
    std::vector<double> in, ring;

    Work(int64_t wc, int64_t c, int n_in, int n_q)
        : WCp((wc + V - 1) / V * V), C(c), pad(R * c), nq(n_q),
          in(size_t(n_in) * size_t(WCp + 2 * pad), 0.0), ring(size_t(K) * n_q * size_t(WCp), 0.0) {}

    int64_t in_stride() const { return WCp + 2 * pad; }
    double* in_row(int q) { return in.data() + q * in_stride(); }  // element e at in_row(q)[pad + e]
    double* ring_row(int64_t image_row, int q) {
        const int64_t slot = (image_row + K) % K;  // image_row >= −R
        return ring.data() + (slot * nq + q) * WCp;
    }
};

// Horizontal 11-tap pass of the NIN padded input rows into the NOUT ring rows `out`, all WCp elements (the
// ones past WC are never read back as results). in[q][pad + e + (k − R)·C] is tap k of element e;
// step(g_k, taps, acc, h) adds tap k's contribution to the accumulators of half h of the chunk.
template <int NIN, int NOUT, class Step>
inline void horizontal(Work& w, const double* g, double* const* out, Step step) {
    const double* in[NIN];
    for (int q = 0; q < NIN; ++q) in[q] = w.in_row(q);
    const int64_t C = w.C;
    for (int64_t e0 = 0; e0 < w.WCp; e0 += V) {
        vd acc[NOUT][2];
        for (int q = 0; q < NOUT; ++q) acc[q][0] = acc[q][1] = vd{};
        for (int k = 0; k < K; ++k) {
            const vd gk = splat(g[k]);
            const int64_t o = e0 + k * C;  // = pad + e0 + (k − R)·C
            for (int h = 0; h < 2; ++h) {
                vd v[NIN];
                for (int q = 0; q < NIN; ++q) v[q] = load(in[q] + o + h * L);
                step(gk, v, acc, h);
            }
        }
        for (int q = 0; q < NOUT; ++q) {
            store(out[q] + e0, acc[q][0]);
            store(out[q] + e0 + L, acc[q][1]);
        }
    }
}

// The K ring rows (quantity 0) that output row i sums: image rows i − R .. i + R; quantity q is at + q·WCp.
inline void window_rows(Work& w, int64_t i, const double** rows) {
    for (int k = 0; k < K; ++k) rows[k] = w.ring_row(i + k - R, 0);
}

// Vertical 11-tap sum for one output row, chunk e0: acc[q][h] = Σ_k g[k] rows[k][q·WCp + e0 + h·L ..].
template <int NQ>
inline void vertical(const double* const* rows, int64_t WCp, const double* g, int64_t e0, vd (*acc)[2]) {
    for (int q = 0; q < NQ; ++q) acc[q][0] = acc[q][1] = vd{};
    for (int k = 0; k < K; ++k) {
        const vd gk = splat(g[k]);
        const double* src = rows[k] + e0;
        for (int q = 0; q < NQ; ++q) {
            acc[q][0] += gk * load(src + q * WCp);
            acc[q][1] += gk * load(src + q * WCp + L);
        }
    }
}

// Write the V results of a chunk (only the n <= V valid ones of the last chunk).
template <class T>
inline void write_chunk(T* dst, const vd* v, int64_t n) {
    if (n >= V) {
        store_out(dst, v[0]);
        store_out(dst + L, v[1]);
        return;
    }
    T tmp[V];
    store_out(tmp, v[0]);
    store_out(tmp + L, v[1]);
    for (int64_t t = 0; t < n; ++t) dst[t] = tmp[t];
}

// Split H rows into bands and run body(work, i0, i1) on each, one band per thread.
template <class Body>
void for_bands(int64_t H, int64_t WC, int64_t C, int nin, int nq, int nthreads, Body body) {
    const int64_t max_bands = std::max<int64_t>(1, H / MIN_BAND_ROWS);
    const int nt = (H * WC >= MIN_PARALLEL) ? (int)std::min<int64_t>(nthreads, max_bands) : 1;
#pragma omp parallel num_threads(nt) if (nt > 1)
    {
        const int64_t team = omp_get_num_threads(), id = omp_get_thread_num();
        const int64_t i0 = H * id / team, i1 = H * (id + 1) / team;
        if (i1 > i0) {
            Work w(WC, C, nin, nq);
            body(w, i0, i1);
        }
    }
}

template <class T>
void fill_row(double* dst, const T* src, int64_t n) {
    for (int64_t e = 0; e < n; ++e) dst[e] = double(src[e]);
}

template <class T>
int forward(int64_t H, int64_t W, int64_t C, const T* x, const T* y, const double* g, double c1, double c2, T* map,
            T* coef, int nthreads) {
    const int64_t WC = W * C, N = H * WC;
    if (N == 0) return 0;
    const vd C1 = splat(c1), C2 = splat(c2), two = splat(2.0), one = splat(1.0);
    for_bands(H, WC, C, 2, 5, nthreads, [&](Work& w, int64_t i0, int64_t i1) {
        // Horizontal pass of image row r (zeros outside the image) into its ring slot.
        auto advance = [&](int64_t r) {
            double* out[5];
            for (int q = 0; q < 5; ++q) out[q] = w.ring_row(r, q);
            if (r < 0 || r >= H) {
                for (int q = 0; q < 5; ++q) std::fill(out[q], out[q] + w.WCp, 0.0);
                return;
            }
            fill_row(w.in_row(0) + w.pad, x + r * WC, WC);
            fill_row(w.in_row(1) + w.pad, y + r * WC, WC);
            horizontal<2, 5>(w, g, out, [](vd gk, const vd* v, vd (*acc)[2], int h) {
                const vd ga = gk * v[0], gb = gk * v[1];
                acc[0][h] += ga;
                acc[1][h] += gb;
                acc[2][h] += ga * v[0];
                acc[3][h] += gb * v[1];
                acc[4][h] += ga * v[1];
            });
        };
        for (int64_t r = i0 - R; r < i0 + R; ++r) advance(r);
        for (int64_t i = i0; i < i1; ++i) {
            advance(i + R);
            const double* rows[K];
            window_rows(w, i, rows);
            for (int64_t e0 = 0; e0 < WC; e0 += V) {
                vd m[5][2];
                vertical<5>(rows, w.WCp, g, e0, m);
                vd s[2], a1[2], a2[2], b1[2], b2[2];
                for (int h = 0; h < 2; ++h) {
                    // B1 = A1 + (μx − μy)², B2 = A2 + (E[x²] + E[y²] − 2E[xy]) − (μx − μy)²: the same
                    // quantities, written so that x = y gives B1 = A1, B2 = A2 and S = 1 exactly.
                    const vd mx = m[0][h], my = m[1][h], d = mx - my;
                    a1[h] = two * (mx * my) + C1;
                    a2[h] = two * (m[4][h] - mx * my) + C2;
                    b1[h] = a1[h] + d * d;
                    b2[h] = a2[h] + ((m[2][h] + m[3][h] - two * m[4][h]) - d * d);
                    s[h] = (a1[h] * a2[h]) / (b1[h] * b2[h]);
                }
                const int64_t o = i * WC + e0, n = WC - e0;
                write_chunk(map + o, s, n);
                if (coef) {
                    vd c_mu[2], c_xx[2], c_xy[2];
                    for (int h = 0; h < 2; ++h) {
                        const vd mx = m[0][h], my = m[1][h];
                        const vd inv = one / (b1[h] * b2[h]), inv_b1 = b2[h] * inv, inv_b2 = b1[h] * inv;
                        c_mu[h] = two * my * (a2[h] - a1[h]) * inv + two * mx * s[h] * (inv_b2 - inv_b1);
                        c_xx[h] = -s[h] * inv_b2;
                        c_xy[h] = two * a1[h] * inv;
                    }
                    write_chunk(coef + o, c_mu, n);
                    write_chunk(coef + N + o, c_xx, n);
                    write_chunk(coef + 2 * N + o, c_xy, n);
                }
            }
        }
    });
    return 0;
}

template <class T>
int backward(int64_t H, int64_t W, int64_t C, const T* x, const T* y, const double* g, const T* coef, const T* g_map,
             T* g_x, int nthreads) {
    const int64_t WC = W * C, N = H * WC;
    if (N == 0) return 0;
    const vd two = splat(2.0);
    for_bands(H, WC, C, 3, 3, nthreads, [&](Work& w, int64_t i0, int64_t i1) {
        auto advance = [&](int64_t r) {
            double* out[3];
            for (int q = 0; q < 3; ++q) out[q] = w.ring_row(r, q);
            if (r < 0 || r >= H) {
                for (int q = 0; q < 3; ++q) std::fill(out[q], out[q] + w.WCp, 0.0);
                return;
            }
            const int64_t o = r * WC;
            for (int q = 0; q < 3; ++q) {
                double* dst = w.in_row(q) + w.pad;
                const T* c = coef + q * N + o;
                const T* gm = g_map + o;
                for (int64_t e = 0; e < WC; ++e) dst[e] = double(gm[e]) * double(c[e]);
            }
            horizontal<3, 3>(w, g, out, [](vd gk, const vd* v, vd (*acc)[2], int h) {
                acc[0][h] += gk * v[0];
                acc[1][h] += gk * v[1];
                acc[2][h] += gk * v[2];
            });
        };
        for (int64_t r = i0 - R; r < i0 + R; ++r) advance(r);
        for (int64_t i = i0; i < i1; ++i) {
            advance(i + R);
            const double* rows[K];
            window_rows(w, i, rows);
            for (int64_t e0 = 0; e0 < WC; e0 += V) {
                vd b[3][2];
                vertical<3>(rows, w.WCp, g, e0, b);
                const int64_t o = i * WC + e0, n = WC - e0;
                vd gx[2];
                for (int h = 0; h < 2; ++h) {
                    vd xv, yv;
                    if (n >= V) {
                        xv = load_in(x + o + h * L);
                        yv = load_in(y + o + h * L);
                    } else {  // last chunk: only n valid inputs
                        double xt[L] = {}, yt[L] = {};
                        for (int l = 0; l < L; ++l) {
                            const int64_t t = h * L + l;
                            if (t < n) {
                                xt[l] = double(x[o + t]);
                                yt[l] = double(y[o + t]);
                            }
                        }
                        xv = load(xt);
                        yv = load(yt);
                    }
                    gx[h] = b[0][h] + two * xv * b[1][h] + yv * b[2][h];
                }
                write_chunk(g_x + o, gx, n);
            }
        }
    });
    return 0;
}

bool bad_args(int64_t H, int64_t W, int64_t C, int64_t dtype, int64_t nthreads) {
    return H < 0 || W < 0 || C < 0 || (dtype != 0 && dtype != 1) || nthreads < 1;
}

}  // namespace

extern "C" {

// x, y (H, W, C) → map (H, W, C); coef (3, H, W, C) or NULL (forward only). dtype 0: float32, 1: float64
// (x, y, map, coef all in it); g1d: 11 float64 taps. Returns 0, or −1 for bad arguments.
int gs_ssim_forward(int64_t H, int64_t W, int64_t C, int64_t dtype, const void* x, const void* y, const double* g1d,
                    double c1, double c2, void* map, void* coef, int64_t nthreads) {
    if (bad_args(H, W, C, dtype, nthreads) || !x || !y || !g1d || !map) return -1;
    if (dtype == 0)
        return forward<float>(H, W, C, (const float*)x, (const float*)y, g1d, c1, c2, (float*)map, (float*)coef,
                              (int)nthreads);
    return forward<double>(H, W, C, (const double*)x, (const double*)y, g1d, c1, c2, (double*)map, (double*)coef,
                           (int)nthreads);
}

// x, y, coef from gs_ssim_forward and g_map = dL/dmap (H, W, C) → g_x = dL/dx (H, W, C); same dtype convention.
int gs_ssim_backward(int64_t H, int64_t W, int64_t C, int64_t dtype, const void* x, const void* y, const double* g1d,
                     const void* coef, const void* g_map, void* g_x, int64_t nthreads) {
    if (bad_args(H, W, C, dtype, nthreads) || !x || !y || !g1d || !coef || !g_map || !g_x) return -1;
    if (dtype == 0)
        return backward<float>(H, W, C, (const float*)x, (const float*)y, g1d, (const float*)coef,
                               (const float*)g_map, (float*)g_x, (int)nthreads);
    return backward<double>(H, W, C, (const double*)x, (const double*)y, g1d, (const double*)coef,
                            (const double*)g_map, (double*)g_x, (int)nthreads);
}

}  // extern "C"
