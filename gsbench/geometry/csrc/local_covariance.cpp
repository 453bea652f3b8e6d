// Covariance of each Gaussian's kNN neighbourhood (IBGS, paper Eq. 4) and its backward, float64 results from
// float32 or float64 means. Python API and the PyTorch reference: gsbench/geometry/local_geometry.py
// (`local_covariance`, `local_covariance_reference`); tests: tests/test_local_covariance_fused.py.
//
// Layout: means (N, 3) C-contiguous, float32 or float64; index (N, K) int64 (neighbour rows, each in [0, N));
// C and g_C (N, 3, 3) float64; g_means (N, 3) float64.
//
// Forward, per Gaussian i with the member set P_i = {x_i (when include_self)} ∪ {x_index[i, k] : k < K}, n = |P_i|:
//   m = (1/n) Σ_{p∈P_i} p,   C_i = (1/n) Σ_{p∈P_i} (p − m)(p − m)ᵀ + jitter · I.
// Backward, for G_i = dL/dC_i: C_i is a quadratic form in the centred points and Σ (p − m) = 0, so the
// path through m contributes nothing and
//   dL/dp = (1/n) (G_i + G_iᵀ)(p − m)   for every member p,
// which is added to the member's row of g_means. The per-member gradients are computed in parallel into a
// (N, n, 3) buffer and scattered serially, in member order, so the sum is the same on any thread count.
#include <cstddef>
#include <cstdint>
#include <omp.h>
#include <vector>

namespace {

// Neighbourhoods fewer than this run on the calling thread.
constexpr int64_t MIN_PARALLEL = 2048;

// Row of member j (0 <= j < n) of neighbourhood i.
inline int64_t member(const int64_t* index, int64_t K, bool self, int64_t i, int64_t j) {
    return self ? (j == 0 ? i : index[i * K + j - 1]) : index[i * K + j];
}

template <typename T>
inline void load(const T* x, int64_t row, double p[3]) {
    for (int a = 0; a < 3; ++a) p[a] = static_cast<double>(x[3 * row + a]);
}

// The centroid m of neighbourhood i.
template <typename T>
inline void centroid(const T* x, const int64_t* index, int64_t K, bool self, int64_t n, int64_t i, double m[3]) {
    m[0] = m[1] = m[2] = 0.0;
    for (int64_t j = 0; j < n; ++j) {
        double p[3];
        load(x, member(index, K, self, i, j), p);
        for (int a = 0; a < 3; ++a) m[a] += p[a];
    }
    for (int a = 0; a < 3; ++a) m[a] /= static_cast<double>(n);
}

template <typename T>
void forward(int64_t N, int64_t K, bool self, const T* x, const int64_t* index, double jitter, double* C,
             int64_t nthreads) {
    const int64_t n = K + (self ? 1 : 0);
#pragma omp parallel for schedule(static) num_threads(nthreads < 1 ? 1 : (int)nthreads) if (N >= MIN_PARALLEL)
    for (int64_t i = 0; i < N; ++i) {
        double m[3], s[9] = {0.0};
        centroid(x, index, K, self, n, i, m);
        for (int64_t j = 0; j < n; ++j) {
            double p[3];
            load(x, member(index, K, self, i, j), p);
            for (int a = 0; a < 3; ++a) p[a] -= m[a];
            for (int a = 0; a < 3; ++a)
                for (int b = 0; b < 3; ++b) s[3 * a + b] += p[a] * p[b];
        }
        for (int e = 0; e < 9; ++e) C[9 * i + e] = s[e] / static_cast<double>(n) + (e % 4 == 0 ? jitter : 0.0);
    }
}

template <typename T>
void backward(int64_t N, int64_t K, bool self, const T* x, const int64_t* index, const double* gC, double* g_means,
              int64_t nthreads) {
    const int64_t n = K + (self ? 1 : 0);
    // every entry is written below: the calling thread's buffer, kept between calls (no zero fill, no fresh
    // pages each step); the OpenMP threads write through the pointer (their own thread_local would be empty)
    static thread_local std::vector<double> buffer;
    if (buffer.size() < static_cast<size_t>(N * n * 3)) buffer.resize(static_cast<size_t>(N * n * 3));
    double* const per_member = buffer.data();
#pragma omp parallel for schedule(static) num_threads(nthreads < 1 ? 1 : (int)nthreads) if (N >= MIN_PARALLEL)
    for (int64_t i = 0; i < N; ++i) {
        double m[3], S[9];
        centroid(x, index, K, self, n, i, m);
        for (int a = 0; a < 3; ++a)
            for (int b = 0; b < 3; ++b) S[3 * a + b] = (gC[9 * i + 3 * a + b] + gC[9 * i + 3 * b + a]) / static_cast<double>(n);
        for (int64_t j = 0; j < n; ++j) {
            double p[3];
            load(x, member(index, K, self, i, j), p);
            for (int a = 0; a < 3; ++a) p[a] -= m[a];
            double* out = &per_member[3 * (i * n + j)];
            for (int a = 0; a < 3; ++a) out[a] = S[3 * a] * p[0] + S[3 * a + 1] * p[1] + S[3 * a + 2] * p[2];
        }
    }
    for (int64_t e = 0; e < 3 * N; ++e) g_means[e] = 0.0;
    for (int64_t i = 0; i < N; ++i)
        for (int64_t j = 0; j < n; ++j) {
            const int64_t row = member(index, K, self, i, j);
            for (int a = 0; a < 3; ++a) g_means[3 * row + a] += per_member[3 * (i * n + j) + a];
        }
}

}  // namespace

extern "C" {

// C (N, 3, 3) float64 (header). dtype 0: float32 means, 1: float64. Returns 0, or 1 on bad sizes or an index
// outside [0, N).
int gs_local_covariance_forward(int64_t N, int64_t K, int64_t include_self, int64_t dtype, const void* means,
                                const int64_t* index, double jitter, double* C, int64_t nthreads) {
    if (N < 0 || K < 0 || (K == 0 && !include_self)) return 1;
    for (int64_t e = 0; e < N * K; ++e)
        if (index[e] < 0 || index[e] >= N) return 1;
    if (dtype == 1) forward(N, K, include_self != 0, static_cast<const double*>(means), index, jitter, C, nthreads);
    else forward(N, K, include_self != 0, static_cast<const float*>(means), index, jitter, C, nthreads);
    return 0;
}

// g_means (N, 3) float64 = dL/dmeans for g_C = dL/dC (header).
int gs_local_covariance_backward(int64_t N, int64_t K, int64_t include_self, int64_t dtype, const void* means,
                                 const int64_t* index, const double* g_C, double* g_means, int64_t nthreads) {
    if (N < 0 || K < 0 || (K == 0 && !include_self)) return 1;
    if (dtype == 1) backward(N, K, include_self != 0, static_cast<const double*>(means), index, g_C, g_means, nthreads);
    else backward(N, K, include_self != 0, static_cast<const float*>(means), index, g_C, g_means, nthreads);
    return 0;
}

}  // extern "C"
