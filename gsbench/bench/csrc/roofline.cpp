// gsbench roofline probes (gsbench/bench/roofline.py): the machine's memory bandwidth (a STREAM triad) and its
// float32 fused multiply-add peak, on `threads` OpenMP threads. Plain C ABI (ctypes).

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <omp.h>

extern "C" {

// Best seconds of `repeats` triads a[i] = b[i] + s c[i] over n floats (the caller's arrays, first touched here
// by the same threads and schedule).
double gs_triad_seconds(float* a, const float* b, const float* c, int64_t n, int repeats, int threads) {
    double best = 1e30;
    for (int r = 0; r < repeats; ++r) {
        const auto t0 = std::chrono::steady_clock::now();
#pragma omp parallel for num_threads(threads) schedule(static)
        for (int64_t i = 0; i < n; ++i) a[i] = b[i] + 1.5f * c[i];
        const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        best = std::min(best, s);
    }
    return best;
}

// Best seconds of `repeats` in-place updates a[i] += s c[i] over n floats: the access pattern of an optimizer
// step (its arrays read and written back in place, so no write allocates a line it has not read).
double gs_update_seconds(float* a, const float* c, int64_t n, int repeats, int threads) {
    double best = 1e30;
    for (int r = 0; r < repeats; ++r) {
        const auto t0 = std::chrono::steady_clock::now();
#pragma omp parallel for num_threads(threads) schedule(static)
        for (int64_t i = 0; i < n; ++i) a[i] += 1e-7f * c[i];
        const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        best = std::min(best, s);
    }
    return best;
}

// Seconds of `iters` rounds of 16 independent 16-wide float FMA chains per thread (2 flops per lane per FMA):
// flops = threads × iters × 16 chains × 16 lanes × 2. The chains' results are returned in `sink`.
typedef float v16 __attribute__((vector_size(64)));

double gs_fma_seconds(int64_t iters, int threads, float* sink) {
    const auto t0 = std::chrono::steady_clock::now();
#pragma omp parallel num_threads(threads)
    {
        v16 acc[16];
        const v16 x = (v16){} + 0.999999f, y = (v16){} + 1e-7f;
        for (int k = 0; k < 16; ++k) acc[k] = (v16){} + (float)(k + omp_get_thread_num());
        for (int64_t it = 0; it < iters; ++it) {
#pragma GCC unroll 16
            for (int k = 0; k < 16; ++k) acc[k] = acc[k] * x + y;
        }
        float total = 0.0f;
        for (int k = 0; k < 16; ++k)
            for (int l = 0; l < 16; ++l) total += acc[k][l];
#pragma omp atomic
        *sink += total;
    }
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

}  // extern "C"
