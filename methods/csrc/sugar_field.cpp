// Fused SuGaR neighbour field and normal average (the regularisers' per-pair work, gsbench.methods.sugar_terms)
// and their backwards, float32 and float64; Python API and the PyTorch references: methods/sugar_field.py; tests:
// tests/test_sugar_field.py. Plain C ABI, OpenMP.
//
// Inputs: samples x (M, 3), means μ (N, 3), rotations R (N, 3, 3) (row-major), scales s (N, 3) (> 0),
// opacities o (N,), normals n (N, 3), smallest scales σ (N,), each sample's Gaussian g = source[m] (M,) and
// neighbour indices idx (M, K), int64 in [0, N), all C-contiguous; the floating inputs in one dtype T. The
// pair p = (m, k) (p = m·K + k) joins sample m and Gaussian j = idx[m, k]. All arithmetic is float64
// whatever T (inputs converted on load, results rounded once on store), so float32 results are the float64
// results rounded, up to the roundings to T noted below.
//
// Field (`gs_sugar_field_*`). With A = R/s (R's columns divided by the scales, A[c][e] = R[c][e] / s[e]):
//   d = x_m − μ_j,   l_e = Σ_c d_c A_j[c][e]   (= (diag(1/s) Rᵀ d)_e),   q = min(Σ_e l_e², qmax),
//   c[m, k] = o_j · exp(−q / 2)                                        (contributions (M, K))
// (q >= 0, so the reference's clamp(q, 0, qmax) is the min). exp is `exp_neg_half` below (4 lanes, within 1 ulp
// of std::exp; 0 below exp(−708), where the reference gives subnormals < 1e-307).
// Backward, for G = dL/dc (M, K): with e = exp(−q/2) (q clamped) and the clamp's gradient 1 where
// Σ l² <= qmax and 0 above (as torch.clamp's),
//   ∂L/∂o_j += G e,   2 ∂L/∂q = −G o_j e [Σ l² <= qmax],   ∂L/∂l = 2 ∂L/∂q · l,   ∂L/∂d = A_j ∂L/∂l,
//   ∂L/∂x_m += ∂L/∂d,    ∂L/∂μ_j −= ∂L/∂d,    ∂L/∂A_j[c][e] += d_c ∂L/∂l_e,
// summed over all pairs, and through A = R/s: ∂L/∂R[c][e] = ∂L/∂A[c][e] / s_e,
// ∂L/∂s_e = −Σ_c ∂L/∂A[c][e] A[c][e] / s_e. Pass 1 runs over the samples (OpenMP over m): it sums ∂L/∂x_m
// over its K pairs and stores each pair's (d, ∂L/∂l, G e), rounded to T, at the pair's place in the list of
// its Gaussian's pairs (`sort_pairs`); pass 2 runs over the Gaussians (OpenMP over j) and sums their pairs'
// terms in increasing p, reading them contiguously; ∂L/∂μ_j is formed as −A_j Σ ∂L/∂l.
//
// Normal average (`gs_sugar_normal_*`), SuGaR's weighted neighbour normal: per pair, with the flip
// f = sign⟨n_j, n_g⟩ (0 at 0, as torch.sign) and d = x_m − μ_j,
//   w = κ c[m, k] |⟨d, n_j⟩| |f| / max(σ_j, σmin)²,   v = w / max(Σ_k w, wmin) · f   (rounded to T),
//   a_m = Σ_k v n_j                                                     (out (M, 3))
// (|f| zeroes w where the reference's flipped normal f n_j is 0). The weights v (M, K) are stored for the
// backward, which differentiates a with respect to the n_j of the sum only (SuGaR detaches the weights; the
// flip is piecewise constant): ∂L/∂n_j = Σ over the pairs of j of v ∂L/∂a_m (OpenMP over j, in increasing p).
//
// Every gradient row has one writer and a fixed summation order, so the gradients are bitwise the same for
// any thread count (training resumes exactly). The per-Gaussian sums run over the pairs of each Gaussian
// listed by a stable counting sort of idx (`sort_pairs`; M·K < 2³¹). Memory: the field packs each Gaussian's
// A, μ, o, s into one 64-byte-aligned float64 record, so a pair reads two cache lines instead of four arrays;
// the normal average packs n, μ, σ likewise (in T: 32 bytes in float32). Scratch (the records, the pair lists,
// the field backward's per-pair terms, P·8 values of T) is kept per calling thread between calls: page faults
// on fresh allocations cost more than the kernels.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <omp.h>
#include <vector>

namespace {

// Fewer pairs than this run on the calling thread (a parallel region costs more than they do).
constexpr int64_t MIN_PARALLEL = 4096;
constexpr int L = 4;  // doubles per vector

typedef double vd __attribute__((vector_size(L * sizeof(double))));
typedef int64_t vi __attribute__((vector_size(L * sizeof(int64_t))));

// exp(−q/2) of L values q >= 0: x = −q/2 = n ln2 + r (n = round(x / ln2), Cody–Waite ln2 = hi + lo with
// n·hi exact), exp(r) by its degree-13 Taylor polynomial (|r| <= ln2/2: truncation < 1e-17 relative),
// times 2ⁿ built in the exponent bits; 0 where x < −708 (2ⁿ would be subnormal).
inline vd exp_neg_half(vd q) {
    constexpr double LOG2E = 1.4426950408889634, LN2_HI = 6.93147180369123816490e-01,
                     LN2_LO = 1.90821492927058770002e-10, SHIFT = 6755399441055744.0;  // 1.5 · 2⁵²
    constexpr double XMIN = -708.0;
    const vd x0 = -0.5 * q;
    const vi keep = x0 >= XMIN;
    const vd x = x0 < XMIN ? vd{} + XMIN : x0;
    const vd t = x * LOG2E + SHIFT;  // round to nearest: n sits in the low mantissa bits of t
    const vd n = t - SHIFT;
    const vd r = (x - n * LN2_HI) - n * LN2_LO;
    vd p = vd{} + 1.0 / 6227020800.0;  // 1/13!
    constexpr double INV_FACT[13] = {1.0 / 479001600.0, 1.0 / 39916800.0, 1.0 / 3628800.0, 1.0 / 362880.0,
                                     1.0 / 40320.0, 1.0 / 5040.0, 1.0 / 720.0, 1.0 / 120.0, 1.0 / 24.0,
                                     1.0 / 6.0, 0.5, 1.0, 1.0};
    for (double c : INV_FACT) p = p * r + c;
    vi bits;
    std::memcpy(&bits, &t, sizeof(vi));
    bits = (bits - int64_t(0x4338000000000000) + 1023) << 52;  // bits(t) = bits(SHIFT) + n
    bits &= keep;
    vd scale;
    std::memcpy(&scale, &bits, sizeof(vd));
    return p * scale;
}

// exp(−q/2) of n values in place; q has room for n rounded up to L.
inline void exp_neg_half(double* q, int64_t n) {
    for (int64_t i = 0; i < n; i += L) {
        vd v;
        std::memcpy(&v, q + i, sizeof(vd));
        v = exp_neg_half(v);
        std::memcpy(q + i, &v, sizeof(vd));
    }
}

inline int64_t round_up(int64_t n) { return (n + L - 1) / L * L; }

// One Gaussian in float64: A = R/s (row-major), μ, o, s (two cache lines).
struct alignas(64) Record {
    double a[9], mu[3], o, s[3];
};

template <typename T>
const Record* pack(int64_t N, const T* means, const T* rot, const T* scales, const T* opac, int nthreads,
                   bool parallel) {
    static thread_local std::vector<Record> records;
    records.resize(N);
    Record* rec = records.data();
#pragma omp parallel for num_threads(nthreads) schedule(static) if (parallel)
    for (int64_t j = 0; j < N; ++j) {
        for (int c = 0; c < 3; ++c) {
            for (int e = 0; e < 3; ++e)
                rec[j].a[3 * c + e] = double(rot[9 * j + 3 * c + e]) / double(scales[3 * j + e]);
            rec[j].mu[c] = means[3 * j + c];
            rec[j].s[c] = scales[3 * j + c];
        }
        rec[j].o = opac[j];
    }
    return rec;
}

// One Gaussian for the normal average: n, μ, σ: 32 bytes (float) / 64 bytes (double).
template <typename T>
struct alignas(32) NormalRecord {
    T n[3], mu[3], min_scale, pad;
};

template <typename T>
const NormalRecord<T>* pack_normals(int64_t N, const T* normals, const T* means, const T* min_scales, int nthreads,
                                    bool parallel) {
    static thread_local std::vector<NormalRecord<T>> records;
    records.resize(N);
    NormalRecord<T>* rec = records.data();
#pragma omp parallel for num_threads(nthreads) schedule(static) if (parallel)
    for (int64_t j = 0; j < N; ++j) {
        for (int c = 0; c < 3; ++c) {
            rec[j].n[c] = normals[3 * j + c];
            rec[j].mu[c] = means[3 * j + c];
        }
        rec[j].min_scale = min_scales[j];
    }
    return rec;
}

struct Pair {
    double d[3], l[3], q;  // q unclamped
};

inline Pair pair_at(const double* xm, const Record& g) {
    Pair p;
    for (int c = 0; c < 3; ++c) p.d[c] = xm[c] - g.mu[c];
    p.q = 0.0;
    for (int e = 0; e < 3; ++e) {
        p.l[e] = p.d[0] * g.a[e] + p.d[1] * g.a[3 + e] + p.d[2] * g.a[6 + e];
        p.q += p.l[e] * p.l[e];
    }
    return p;
}

// The pairs of Gaussian j: pair[start[j] .. start[j + 1]), in increasing p (int32: M·K < 2³¹); pair p sits at
// pos[p]. For the idx (N Gaussians) kept in `key`.
struct PairLists {
    std::vector<int64_t> key;
    int64_t n = -1;
    std::vector<int32_t> start, pair, pos, slot;
};

// Stable counting sort of the pairs p < P by idx[p]. The pairs are cut into `chunks` ranges; each counts its
// keys (slot: chunks × N), the slots are laid out j-major then chunk, and each range scatters its pairs. The
// field's and the normals' backward sort the same idx: the last sort is reused when idx is equal (compared
// in full, much cheaper than sorting).
const PairLists& sort_pairs(int64_t P, int64_t N, const int64_t* idx, int nthreads, bool parallel) {
    static thread_local PairLists s;
    if (s.n == N && int64_t(s.key.size()) == P && std::equal(idx, idx + P, s.key.begin())) return s;
    s.key.assign(idx, idx + P);
    s.n = N;
    const int chunks = parallel ? nthreads : 1;
    s.start.resize(N + 1);
    s.pair.resize(P);
    s.pos.resize(P);
    s.slot.assign(chunks * N, 0);
    int32_t* slot = s.slot.data();
    int32_t* pair = s.pair.data();
    int32_t* pos = s.pos.data();
#pragma omp parallel for num_threads(nthreads) schedule(static, 1) if (parallel)
    for (int c = 0; c < chunks; ++c) {
        int32_t* h = slot + c * N;
        for (int64_t p = P * c / chunks; p < P * (c + 1) / chunks; ++p) ++h[idx[p]];
    }
    int32_t next = 0;
    for (int64_t j = 0; j < N; ++j) {
        s.start[j] = next;
        for (int c = 0; c < chunks; ++c) {
            const int32_t n = slot[c * N + j];
            slot[c * N + j] = next;
            next += n;
        }
    }
    s.start[N] = next;
#pragma omp parallel for num_threads(nthreads) schedule(static, 1) if (parallel)
    for (int c = 0; c < chunks; ++c) {
        int32_t* h = slot + c * N;
        for (int64_t p = P * c / chunks; p < P * (c + 1) / chunks; ++p) {
            const int32_t i = h[idx[p]]++;
            pair[i] = int32_t(p);
            pos[p] = i;
        }
    }
    return s;
}

// p / K (the sample of pair p) without an integer division: a float64 estimate, corrected by one.
struct SampleOf {
    int64_t K;
    double inv;
    explicit SampleOf(int64_t k) : K(k), inv(1.0 / double(k)) {}
    int64_t operator()(int64_t p) const {
        int64_t m = int64_t(double(p) * inv);
        m -= int64_t(m * K > p);
        m += int64_t((m + 1) * K <= p);
        return m;
    }
};

bool bad_index(int64_t P, int64_t N, const int64_t* idx) {
    int64_t bad = 0;
    for (int64_t p = 0; p < P; ++p) bad |= int64_t(uint64_t(idx[p]) >= uint64_t(N));
    return bad != 0;
}

template <typename T>
int field_forward(int64_t M, int64_t K, int64_t N, const T* x, const T* means, const T* rot, const T* scales,
                  const T* opac, const int64_t* idx, double qmax, T* out, int nthreads) {
    if (bad_index(M * K, N, idx)) return -2;
    const bool parallel = M * K >= MIN_PARALLEL;
    const Record* rec = pack(N, means, rot, scales, opac, nthreads, parallel);
#pragma omp parallel num_threads(nthreads) if (parallel)
    {
        std::vector<double> e(round_up(K));
#pragma omp for schedule(static)
        for (int64_t m = 0; m < M; ++m) {
            const double xm[3] = {double(x[3 * m]), double(x[3 * m + 1]), double(x[3 * m + 2])};
            const int64_t* row = idx + m * K;
            for (int64_t k = 0; k < K; ++k) e[k] = std::min(pair_at(xm, rec[row[k]]).q, qmax);
            exp_neg_half(e.data(), K);
            for (int64_t k = 0; k < K; ++k) out[m * K + k] = T(rec[row[k]].o * e[k]);
        }
    }
    return 0;
}

// One pair's share of the per-Gaussian gradients (pass 1 → pass 2): d, ∂L/∂l, G e, in T.
template <typename T>
struct alignas(8 * sizeof(T)) PairGrad {
    T d[3], gl[3], ge, pad;
};

template <typename T>
int field_backward(int64_t M, int64_t K, int64_t N, const T* x, const T* means, const T* rot, const T* scales,
                   const T* opac, const int64_t* idx, double qmax, const T* g_out, T* g_x, T* g_means, T* g_rot,
                   T* g_scales, T* g_opac, int nthreads) {
    const int64_t P = M * K;
    if (bad_index(P, N, idx)) return -2;
    const bool parallel = P >= MIN_PARALLEL;
    const Record* rec = pack(N, means, rot, scales, opac, nthreads, parallel);
    const PairLists& lists = sort_pairs(P, N, idx, nthreads, parallel);
    const int32_t* start = lists.start.data();
    const int32_t* pos = lists.pos.data();
    static thread_local std::vector<PairGrad<T>> pair_grads;
    pair_grads.resize(P);
    PairGrad<T>* pg = pair_grads.data();

    // Pass 1: over the samples.
#pragma omp parallel num_threads(nthreads) if (parallel)
    {
        std::vector<Pair> pairs(K);
        std::vector<double> e(round_up(K));
#pragma omp for schedule(static)
        for (int64_t m = 0; m < M; ++m) {
            const double xm[3] = {double(x[3 * m]), double(x[3 * m + 1]), double(x[3 * m + 2])};
            const int64_t* row = idx + m * K;
            for (int64_t k = 0; k < K; ++k) {
                pairs[k] = pair_at(xm, rec[row[k]]);
                e[k] = std::min(pairs[k].q, qmax);
            }
            exp_neg_half(e.data(), K);
            double gx[3] = {0.0, 0.0, 0.0};
            for (int64_t k = 0; k < K; ++k) {
                const Pair& p = pairs[k];
                const Record& g = rec[row[k]];
                const double ge = double(g_out[m * K + k]) * e[k];
                const double gq2 = p.q <= qmax ? -ge * g.o : 0.0;  // 2 ∂L/∂q
                PairGrad<T>& out = pg[pos[m * K + k]];
                for (int c = 0; c < 3; ++c) {
                    out.d[c] = T(p.d[c]);
                    out.gl[c] = T(gq2 * p.l[c]);
                    gx[c] += gq2 * (g.a[3 * c] * p.l[0] + g.a[3 * c + 1] * p.l[1] + g.a[3 * c + 2] * p.l[2]);
                }
                out.ge = T(ge);
            }
            for (int c = 0; c < 3; ++c) g_x[3 * m + c] = T(gx[c]);
        }
    }

    // Pass 2: over the Gaussians.
#pragma omp parallel for num_threads(nthreads) schedule(static) if (parallel)
    for (int64_t j = 0; j < N; ++j) {
        const Record& g = rec[j];
        double ga[9] = {}, gl[3] = {}, go = 0.0;
        for (int64_t i = start[j]; i < start[j + 1]; ++i) {
            const PairGrad<T>& p = pg[i];
            for (int k = 0; k < 3; ++k) {
                const double gk = double(p.gl[k]);
                gl[k] += gk;
                for (int c = 0; c < 3; ++c) ga[3 * c + k] += double(p.d[c]) * gk;
            }
            go += double(p.ge);
        }
        for (int c = 0; c < 3; ++c)
            g_means[3 * j + c] = T(-(g.a[3 * c] * gl[0] + g.a[3 * c + 1] * gl[1] + g.a[3 * c + 2] * gl[2]));
        for (int e = 0; e < 3; ++e) {
            const double se = g.s[e];
            double gs = 0.0;
            for (int c = 0; c < 3; ++c) {
                g_rot[9 * j + 3 * c + e] = T(ga[3 * c + e] / se);
                gs -= ga[3 * c + e] * g.a[3 * c + e];
            }
            g_scales[3 * j + e] = T(gs / se);
        }
        g_opac[j] = T(go);
    }
    return 0;
}

template <typename T>
int normal_forward(int64_t M, int64_t K, int64_t N, const T* normals, const T* x, const T* means,
                   const T* min_scales, const T* contrib, const int64_t* source, const int64_t* idx, double kappa,
                   double scale_min, double sum_min, T* out, T* weights, int nthreads) {
    if (bad_index(M * K, N, idx) || bad_index(M, N, source)) return -2;
    const bool parallel = M * K >= MIN_PARALLEL;
    const NormalRecord<T>* rec = pack_normals(N, normals, means, min_scales, nthreads, parallel);
#pragma omp parallel num_threads(nthreads) if (parallel)
    {
        std::vector<double> w(K), flip(K);
#pragma omp for schedule(static)
        for (int64_t m = 0; m < M; ++m) {
            const T* ng = rec[source[m]].n;
            const int64_t* row = idx + m * K;
            const double xm[3] = {double(x[3 * m]), double(x[3 * m + 1]), double(x[3 * m + 2])};
            double sum = 0.0;
            for (int64_t k = 0; k < K; ++k) {
                const NormalRecord<T>& g = rec[row[k]];
                double dot = 0.0, dist = 0.0;
                for (int c = 0; c < 3; ++c) {
                    dot += double(g.n[c]) * double(ng[c]);
                    dist += (xm[c] - double(g.mu[c])) * double(g.n[c]);
                }
                flip[k] = std::copysign(1.0, dot) * double(dot != 0.0);  // branch-free: the signs are random
                const double s = std::max(double(g.min_scale), scale_min);
                w[k] = kappa * double(contrib[m * K + k]) * std::fabs(dist) * std::fabs(flip[k]) / (s * s);
                sum += w[k];
            }
            const double den = std::max(sum, sum_min);
            double a[3] = {0.0, 0.0, 0.0};
            for (int64_t k = 0; k < K; ++k) {
                const T v = T(w[k] / den * flip[k]);
                weights[m * K + k] = v;
                for (int c = 0; c < 3; ++c) a[c] += double(v) * double(rec[row[k]].n[c]);
            }
            for (int c = 0; c < 3; ++c) out[3 * m + c] = T(a[c]);
        }
    }
    return 0;
}

template <typename T>
int normal_backward(int64_t M, int64_t K, int64_t N, const int64_t* idx, const T* weights, const T* g_out,
                    T* g_normals, int nthreads) {
    const int64_t P = M * K;
    if (bad_index(P, N, idx)) return -2;
    const bool parallel = P >= MIN_PARALLEL;
    const PairLists& lists = sort_pairs(P, N, idx, nthreads, parallel);
    const int32_t* start = lists.start.data();
    const int32_t* pair = lists.pair.data();
    const SampleOf sample_of(K);
#pragma omp parallel for num_threads(nthreads) schedule(static) if (parallel)
    for (int64_t j = 0; j < N; ++j) {
        double g[3] = {0.0, 0.0, 0.0};
        for (int64_t i = start[j]; i < start[j + 1]; ++i) {
            const int64_t p = pair[i], m = sample_of(p);
            const double v = double(weights[p]);
            for (int c = 0; c < 3; ++c) g[c] += v * double(g_out[3 * m + c]);
        }
        for (int c = 0; c < 3; ++c) g_normals[3 * j + c] = T(g[c]);
    }
    return 0;
}

bool bad_args(int64_t M, int64_t K, int64_t N, int64_t dtype, int64_t nthreads) {
    return M < 0 || K < 0 || N < 0 || (dtype != 0 && dtype != 1) || nthreads < 1 || (K > 0 && M > INT32_MAX / K);
}

}  // namespace

extern "C" {

// Contributions out (M, K) of samples x (M, 3) for means (N, 3), rotations (N, 3, 3), scales (N, 3), opacities
// (N,), idx (M, K) int64. dtype 0: float32, 1: float64 (every floating array in it). Returns 0, −1 for bad
// arguments, −2 for an index outside [0, N) (nothing written).
int gs_sugar_field_forward(int64_t M, int64_t K, int64_t N, int64_t dtype, const void* x, const void* means,
                           const void* rot, const void* scales, const void* opac, const int64_t* idx, double qmax,
                           void* out, int64_t nthreads) {
    if (bad_args(M, K, N, dtype, nthreads) || !x || !means || !rot || !scales || !opac || !idx || !out) return -1;
    if (dtype == 0)
        return field_forward<float>(M, K, N, (const float*)x, (const float*)means, (const float*)rot,
                                    (const float*)scales, (const float*)opac, idx, qmax, (float*)out, (int)nthreads);
    return field_forward<double>(M, K, N, (const double*)x, (const double*)means, (const double*)rot,
                                 (const double*)scales, (const double*)opac, idx, qmax, (double*)out, (int)nthreads);
}

// The same inputs and g_out = dL/dout (M, K) → g_x (M, 3), g_means (N, 3), g_rot (N, 3, 3), g_scales (N, 3),
// g_opac (N,), all written in full; same dtype convention and return codes.
int gs_sugar_field_backward(int64_t M, int64_t K, int64_t N, int64_t dtype, const void* x, const void* means,
                            const void* rot, const void* scales, const void* opac, const int64_t* idx, double qmax,
                            const void* g_out, void* g_x, void* g_means, void* g_rot, void* g_scales, void* g_opac,
                            int64_t nthreads) {
    if (bad_args(M, K, N, dtype, nthreads) || !x || !means || !rot || !scales || !opac || !idx || !g_out || !g_x ||
        !g_means || !g_rot || !g_scales || !g_opac)
        return -1;
    if (dtype == 0)
        return field_backward<float>(M, K, N, (const float*)x, (const float*)means, (const float*)rot,
                                     (const float*)scales, (const float*)opac, idx, qmax, (const float*)g_out,
                                     (float*)g_x, (float*)g_means, (float*)g_rot, (float*)g_scales, (float*)g_opac,
                                     (int)nthreads);
    return field_backward<double>(M, K, N, (const double*)x, (const double*)means, (const double*)rot,
                                  (const double*)scales, (const double*)opac, idx, qmax, (const double*)g_out,
                                  (double*)g_x, (double*)g_means, (double*)g_rot, (double*)g_scales,
                                  (double*)g_opac, (int)nthreads);
}

// Normal average out (M, 3) and weights v (M, K) from normals (N, 3), samples x (M, 3), means (N, 3), smallest
// scales (N,), contributions (M, K), source (M,) and idx (M, K) int64; same dtype convention and return codes.
int gs_sugar_normal_forward(int64_t M, int64_t K, int64_t N, int64_t dtype, const void* normals, const void* x,
                            const void* means, const void* min_scales, const void* contrib, const int64_t* source,
                            const int64_t* idx, double kappa, double scale_min, double sum_min, void* out,
                            void* weights, int64_t nthreads) {
    if (bad_args(M, K, N, dtype, nthreads) || !normals || !x || !means || !min_scales || !contrib || !source ||
        !idx || !out || !weights)
        return -1;
    if (dtype == 0)
        return normal_forward<float>(M, K, N, (const float*)normals, (const float*)x, (const float*)means,
                                     (const float*)min_scales, (const float*)contrib, source, idx, kappa, scale_min,
                                     sum_min, (float*)out, (float*)weights, (int)nthreads);
    return normal_forward<double>(M, K, N, (const double*)normals, (const double*)x, (const double*)means,
                                  (const double*)min_scales, (const double*)contrib, source, idx, kappa, scale_min,
                                  sum_min, (double*)out, (double*)weights, (int)nthreads);
}

// idx (M, K), the forward's weights v (M, K) and g_out = dL/dout (M, 3) → g_normals (N, 3), written in full.
int gs_sugar_normal_backward(int64_t M, int64_t K, int64_t N, int64_t dtype, const int64_t* idx,
                             const void* weights, const void* g_out, void* g_normals, int64_t nthreads) {
    if (bad_args(M, K, N, dtype, nthreads) || !idx || !weights || !g_out || !g_normals) return -1;
    if (dtype == 0)
        return normal_backward<float>(M, K, N, idx, (const float*)weights, (const float*)g_out, (float*)g_normals,
                                      (int)nthreads);
    return normal_backward<double>(M, K, N, idx, (const double*)weights, (const double*)g_out,
                                   (double*)g_normals, (int)nthreads);
}

}  // extern "C"
