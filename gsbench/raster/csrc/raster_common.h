// gsbench tile rasterizer: what the compositing (composite.cpp), the depth sort and rectangle binning
// (sort_bin.cpp) and the exact ellipse/tile binning (bin_exact.cpp) share: tile and payload constants, the
// argument struct of the C ABI and the inline math helpers. Built with -ffinite-math-only: no isnan/isinf
// here (inputs are validated in Python) and all sentinels are finite.

#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>
#include <omp.h>
#include <immintrin.h>

namespace {

constexpr int TS = 16;       // tile size
constexpr int TP = TS * TS;  // pixels per tile
constexpr int HL = 8;        // lanes per chunk: a tile row is two chunks, each evaluated only if the box meets it
constexpr int K_EWA = 0, K_RADE = 1, K_RAYMAX = 2, K_SURFEL = 3;

// common payload columns
constexpr int P_MX = 0, P_MY = 1, P_CA = 2, P_CB = 3, P_CC = 4, P_O = 5, P_R = 6, P_G = 7, P_B = 8, P_X = 9;

template <int K> struct NP;
template <> struct NP<K_EWA> { static constexpr int v = 13; };
template <> struct NP<K_RADE> { static constexpr int v = 15; };
template <> struct NP<K_RAYMAX> { static constexpr int v = 24; };
template <> struct NP<K_SURFEL> { static constexpr int v = 21; };

}  // namespace

extern "C" {

// Keep in sync with GsArgs in gsbench/raster/abi.py (ctypes): 8-byte fields only.
struct GsArgs {
    int64_t kernel, dtype, width, height, tiles_x, tiles_y, n_gauss, n_params, nthreads;
    int64_t want_rgb, want_depth, want_median, want_normal, want_dist, detach_dist;
    double fx, fy, cx, cy, near_z, far_z, surfel_k;  // surfel_k: low-pass k in ρ2d = k|Δ|² (0 = off)
    const void* params;         // (N, P)
    const void* bounds;         // (N, 4) xmin xmax ymin ymax
    const void* depth_key;      // (N,) centre z (distortion shift)
    const int32_t* tile_offsets;  // (tiles + 1)
    const int32_t* tile_list;     // (pairs)
    // forward outputs (null if not requested) and saved state
    void* out_rgb;     // (H, W, 3)
    void* out_alpha;   // (H, W)
    void* out_depth;   // (H, W) Σ w z
    void* out_median;  // (H, W)
    void* out_normal;  // (H, W, 3)
    void* out_dist;    // (H, W)
    void* T_final;     // (H, W)
    int32_t* last;     // (H, W)
    int32_t* median_idx;  // (H, W)
    void* M1;          // (H, W)
    void* M2;          // (H, W)
    // backward inputs (null if no gradient)
    const void* g_rgb;
    const void* g_alpha;
    const void* g_depth;
    const void* g_median;
    const void* g_normal;
    const void* g_dist;
    // backward outputs
    void* grad_params;  // (N, P), zero-initialised
    void* absgrad;      // (N,), zero-initialised
    void* proxy;        // (N, 2) raymax densification proxy (pixel units), zero-initialised
    int64_t pairs;      // out: pixel-Gaussian lanes evaluated
    // plane_distance (PGSR, docs/methods/pgsr.md §3.1), appended so the fields above keep their offsets
    int64_t want_plane;
    const void* plane_d;  // (N,) per-Gaussian plane distance d_i = −n_i·μ_i
    void* out_plane;      // (H, W) Σ w d
    const void* g_plane;  // (H, W) backward input (null if no gradient)
    void* grad_plane;     // (N,) dL/dd = Σ_pixels w·g_plane, zero-initialised
};

}  // extern "C"

namespace {

template <typename T> inline T fexp(T x);

// exp for x in [-30, 0] (callers clamp); ~2 ulp, vectorisable (no libm call).
template <> inline float fexp<float>(float x) {
    const float l2e = 1.44269504088896341f;
    float t = x * l2e;
    float nf = std::floor(t + 0.5f);
    float r = x - nf * 0.693359375f;
    r = r - nf * (-2.12194440e-4f);
    float p = 1.9875691500e-4f;
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    p = p * r * r + r + 1.0f;
    int32_t n = (int32_t)nf;
    const int32_t bits = (n + 127) << 23;
    return p * __builtin_bit_cast(float, bits);
}
template <> inline double fexp<double>(double x) { return std::exp(x); }

template <typename T> inline T mapm(T z, T nearz, T farz) {
    return farz / (farz - nearz) * (T(1) - nearz / z);
}
template <typename T> inline T dmapm(T z, T nearz, T farz) {
    return farz * nearz / ((farz - nearz) * z * z);
}

// c ? a : b as a bitwise blend. The lane loops use it for every select that feeds a store: GCC turns a `?:`
// into a branch, and with -fno-signed-zeros proves `x += c ? y : 0` / `x = c ? y : x` a no-op on one side,
// so the vectoriser emits masked stores (vmaskmovps, slow on AVX2) behind a branch per store; a bitwise
// select stays straight-line code. Bit-identical to `?:`.
template <typename T> struct UInt;
template <> struct UInt<float> { using t = uint32_t; };
template <> struct UInt<double> { using t = uint64_t; };
template <> struct UInt<int32_t> { using t = uint32_t; };
template <typename T>
inline T bsel(bool c, T a, T b) {
    using U = typename UInt<T>::t;
    const U m = (U)0 - (U)c;
    return __builtin_bit_cast(T, (U)((__builtin_bit_cast(U, a) & m) | (__builtin_bit_cast(U, b) & ~m)));
}

struct FTZGuard {
    unsigned int csr;
    FTZGuard() : csr(_mm_getcsr()) { _mm_setcsr(csr | 0x8040); }
    ~FTZGuard() { _mm_setcsr(csr); }
};

// software prefetch of a Gaussian's payload and bounds PF list entries ahead (random access into N)
constexpr int PF = 8;
template <int NPK, typename T>
inline void prefetch_gauss(const T* P, const T* BND, int g) {
    const char* p = (const char*)(P + (int64_t)g * NPK);
    for (int off = 0; off < NPK * (int)sizeof(T); off += 64) __builtin_prefetch(p + off, 0, 1);
    __builtin_prefetch(BND + (int64_t)g * 4, 0, 1);
}

// rows of tile (y0..y0+nrows) whose pixel centre lies in [ymin, ymax] (also used for columns)
template <typename T>
inline void row_range(T ymin, T ymax, int y0, int nrows, int& r0, int& r1) {
    T lo = std::min(std::max(ymin, T(y0 - 2)), T(y0 + TS + 2));
    T hi = std::min(std::max(ymax, T(y0 - 2)), T(y0 + TS + 2));
    r0 = std::max(y0, (int)std::ceil(lo - T(0.5)));
    r1 = std::min(y0 + nrows, (int)std::floor(hi - T(0.5)) + 1);
}

// 1/|r| of each pixel of a tile (rade's camera-z depth), once per tile: same expression as per lane.
template <typename T>
inline void fill_invr(T* __restrict invrs, const T* __restrict rxs, int y0, int nrows, T cy, T fy) {
    for (int ly = 0; ly < nrows; ++ly) {
        const T py = T(y0 + ly) + T(0.5);
        const T ry = (py - cy) / fy;
#pragma omp simd
        for (int lx = 0; lx < TS; ++lx) invrs[ly * TS + lx] = T(1) / std::sqrt(rxs[lx] * rxs[lx] + ry * ry + T(1));
    }
}


}  // namespace
