// gsbench tile rasterizer: binning, front-to-back compositing and its reverse pass.
//
// Plain C ABI (called through ctypes; no torch headers, so the build is one fast translation unit).
// Per-Gaussian payload layout: see gsbench/raster/projection.py. Pixel (i, j) is evaluated at
// (i + 0.5, j + 0.5); its ray is ((x - cx)/fx, (y - cy)/fy, 1).
//
// Loop order: per 16x16 tile (OpenMP), Gaussians of the tile in depth order (outer), and the
// 16 pixels of one tile row as SIMD lanes (inner). Rows outside a Gaussian's alpha >= 1/255 box are
// skipped, and so is each 8-lane half of a row that the box's columns miss; this never changes a
// result. The backward walks the list back to front, recomputes alpha, reduces each Gaussian's
// gradient over the tile's lanes, then adds it to a per-thread buffer.
// Determinism: the backward deals tiles round-robin (static, 1), not dynamically, and sums the
// per-thread buffers in thread order, so the gradients are bit-identical from run to run at a given
// thread count (training resumes exactly); the forward writes each pixel once, so its schedule is free.
//
// Built with -ffinite-math-only: no isnan/isinf here (inputs are validated in Python) and all
// sentinels are finite.

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

// Keep in sync with build.py (ctypes): 8-byte fields only.
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

// ---------------------------------------------------------------------------------------------
// Per-lane kernel evaluation, shared by forward and backward. Returns G (before opacity), sets
// `ok` (kernel-specific validity), per-pixel depth z and normal n (when needed).
// ---------------------------------------------------------------------------------------------
template <int K, typename T>
struct Eval {
    T G, z, n0, n1, n2;
    bool ok;
    // intermediates for the backward
    T dx, dy;                                      // pixel - mean2d (ewa/rade), mean2d - pixel (surfel)
    T Ar0, Ar1, Ar2, rAr_inv, nrm_inv, num, q, t;  // raymax
    T Dx, Dy;
    T k0, k1, k2, l0, l1, l2, ip, s0, s1;          // surfel
    bool branch3d;
};

template <int K, typename T>
__attribute__((always_inline)) inline void eval_lane(Eval<K, T>& e, const T* __restrict p, T px, T py, T rx, T ry,
                                                      T invr, T nearz, T surfel_k, bool need_normal) {
    if constexpr (K == K_EWA || K == K_RADE) {
        e.dx = px - p[P_MX];
        e.dy = py - p[P_MY];
        T power = T(-0.5) * (p[P_CA] * e.dx * e.dx + p[P_CC] * e.dy * e.dy) - p[P_CB] * e.dx * e.dy;
        e.ok = power <= T(0);
        e.G = fexp<T>(std::max(power, T(-30)));
        if constexpr (K == K_EWA) {
            e.z = p[P_X];
            e.n0 = p[P_X + 1];
            e.n1 = p[P_X + 2];
            e.n2 = p[P_X + 3];
        } else {
            e.z = (p[P_X] + p[P_X + 1] * e.dx + p[P_X + 2] * e.dy) * invr;
            e.n0 = p[P_X + 3];
            e.n1 = p[P_X + 4];
            e.n2 = p[P_X + 5];
        }
    } else if constexpr (K == K_RAYMAX) {
        const T* a = p + P_X;  // a00 a01 a02 a11 a12 a22, b0 b1 b2, m00 m01 m11, c, ucx, ucy
        e.Ar0 = a[0] * rx + a[1] * ry + a[2];
        e.Ar1 = a[1] * rx + a[3] * ry + a[4];
        e.Ar2 = a[2] * rx + a[4] * ry + a[5];
        T rAr = rx * e.Ar0 + ry * e.Ar1 + e.Ar2;
        e.rAr_inv = T(1) / rAr;
        T br = a[6] * rx + a[7] * ry + a[8];
        e.Dx = rx - a[13];
        e.Dy = ry - a[14];
        e.num = std::max(a[9] * e.Dx * e.Dx + T(2) * a[10] * e.Dx * e.Dy + a[11] * e.Dy * e.Dy, T(0));
        e.q = a[12] * e.num * e.rAr_inv;
        e.t = br * e.rAr_inv;
        e.z = e.t;
        e.ok = e.t > nearz;
        e.G = fexp<T>(std::max(T(-0.5) * e.q, T(-30)));
        if (need_normal) {
            T nn = e.Ar0 * e.Ar0 + e.Ar1 * e.Ar1 + e.Ar2 * e.Ar2;
            e.nrm_inv = T(1) / std::sqrt(std::max(nn, T(1e-30)));
            e.n0 = -e.Ar0 * e.nrm_inv;
            e.n1 = -e.Ar1 * e.nrm_inv;
            e.n2 = -e.Ar2 * e.nrm_inv;
        } else {  // unused; non-zero stores keep GCC from merging them into a memset (blocks vectorisation)
            e.nrm_inv = T(1);
            e.n0 = -e.Ar0;
            e.n1 = -e.Ar1;
            e.n2 = -e.Ar2;
        }
    } else {  // surfel: plane n·x = d (n = camera-facing unit normal), local axes a_u = t_u/s_u, a_v
        const T* X = p + P_X;  // n (3), d, a_u (3), b_u, a_v (3), b_v ; b = μ·a
        const T nr = X[0] * rx + X[1] * ry + X[2];
        // ray parallel to the splat (p.z == 0 in the homogeneous form of docs/methods/2dgs.md §3.2)
        const bool par = std::fabs(nr) < T(1e-7) * (std::fabs(rx) + std::fabs(ry) + T(1));
        e.ip = T(1) / bsel<T>(par, T(1), nr);
        e.t = X[3] * e.ip;  // intersection depth (r_z = 1)
        e.k0 = X[4] * rx + X[5] * ry + X[6];   // r·a_u
        e.l0 = X[8] * rx + X[9] * ry + X[10];  // r·a_v
        e.s0 = e.t * e.k0 - X[7];
        e.s1 = e.t * e.l0 - X[11];
        const T rho3 = e.s0 * e.s0 + e.s1 * e.s1;
        e.dx = p[P_MX] - px;
        e.dy = p[P_MY] - py;
        // the 2DGS paper's object-space low-pass filter, k = 1/σ² = 2 there; surfel_k = 0 switches it off
        const T rho2 = surfel_k * (e.dx * e.dx + e.dy * e.dy);
        e.branch3d = surfel_k <= T(0) || rho3 <= rho2;
        const T rho = bsel<T>(e.branch3d, rho3, rho2);
        e.z = e.t;
        e.ok = !par && e.z >= nearz;
        e.G = fexp<T>(std::max(T(-0.5) * rho, T(-30)));
        e.n0 = X[0];
        e.n1 = X[1];
        e.n2 = X[2];
    }
}

// ---------------------------------------------------------------------------------------------
// Forward
// ---------------------------------------------------------------------------------------------
// MODE: 0 = colour/alpha only; 1 = + depth, median, normal (GEOM); 2 = GEOM + distortion (DIST). In GEOM
// mode the lanes compute depth, median and normal whether requested or not (only the requested ones are
// written): runtime flags inside the lane loop block GCC's vectoriser (invariant-condition selects).
// PL (GEOM only): + the plane distance Σ w d, like one more colour channel from the per-Gaussian d (plane_d).
template <int K, typename T, int MODE, bool PL>
void forward_impl(GsArgs& A) {
    constexpr bool GEOM = MODE >= 1, DIST = MODE == 2;
    static_assert(GEOM || !PL, "the plane distance is a geometry output");
    constexpr int NPK = NP<K>::v;
    const int W = (int)A.width, H = (int)A.height, TX = (int)A.tiles_x, TY = (int)A.tiles_y;
    const T* __restrict P = (const T*)A.params;
    const T* __restrict BND = (const T*)A.bounds;
    const T* __restrict DK = (const T*)A.depth_key;
    const T fx = (T)A.fx, fy = (T)A.fy, cx = (T)A.cx, cy = (T)A.cy, nearz = (T)A.near_z, farz = (T)A.far_z,
            surfel_k = (T)A.surfel_k;
    const bool w_rgb = A.want_rgb, w_depth = A.want_depth, w_med = A.want_median, w_nrm = A.want_normal;
    T* o_rgb = (T*)A.out_rgb;
    T* o_alpha = (T*)A.out_alpha;
    T* o_depth = (T*)A.out_depth;
    T* o_med = (T*)A.out_median;
    T* o_nrm = (T*)A.out_normal;
    T* o_dist = (T*)A.out_dist;
    T* o_T = (T*)A.T_final;
    T* o_M1 = (T*)A.M1;
    T* o_M2 = (T*)A.M2;
    const T* __restrict PD = (const T*)A.plane_d;
    T* o_pl = (T*)A.out_plane;
    int64_t pairs = 0;
    const int ntiles = TX * TY;

#pragma omp parallel num_threads((int)A.nthreads) reduction(+ : pairs)
    {
        FTZGuard ftz;
        alignas(64) T Tr[TP], act[TP], cr[TP], cg[TP], cb[TP], wa[TP];
        alignas(64) T dep[TP], med[TP], n0[TP], n1[TP], n2[TP], m1[TP], m2[TP];
        alignas(64) T pl[PL ? TP : 1];
        alignas(64) int32_t lastk[TP], medi[TP];
        alignas(64) T rxs[TS];
        alignas(64) T invrs[K == K_RADE && GEOM ? TP : 1];
#pragma omp for schedule(dynamic, 1)
        for (int tile = 0; tile < ntiles; ++tile) {
            const int tx = tile % TX, ty = tile / TX;
            const int x0 = tx * TS, y0 = ty * TS;
            const int ncols = std::min(TS, W - x0), nrows = std::min(TS, H - y0);
            for (int i = 0; i < TP; ++i) {
                const int ly = i / TS, lx = i % TS;
                Tr[i] = T(1);
                act[i] = (ly < nrows && lx < ncols) ? T(1) : T(0);
                cr[i] = cg[i] = cb[i] = wa[i] = T(0);
                lastk[i] = 0;
                if constexpr (GEOM) {
                    dep[i] = med[i] = n0[i] = n1[i] = n2[i] = m1[i] = m2[i] = T(0);
                    medi[i] = -1;
                }
                if constexpr (PL) pl[i] = T(0);
            }
            for (int lx = 0; lx < TS; ++lx) rxs[lx] = (T(x0 + lx) + T(0.5) - cx) / fx;
            if constexpr (K == K_RADE && GEOM) fill_invr<T>(invrs, rxs, y0, nrows, cy, fy);
            int ndone = TP - nrows * ncols;
            const int beg = A.tile_offsets[tile], end = A.tile_offsets[tile + 1];
            T m0 = T(0);
            if (DIST && end > beg) m0 = mapm<T>(DK[A.tile_list[beg]], nearz, farz);
            for (int k = beg; k < end && ndone < TP; ++k) {
                if (k + PF < end) {
                    prefetch_gauss<NPK, T>(P, BND, A.tile_list[k + PF]);
                    if constexpr (PL) __builtin_prefetch(PD + A.tile_list[k + PF], 0, 1);
                }
                const int g = A.tile_list[k];
                const T* __restrict p = P + (int64_t)g * NPK;
                const T* bnd = BND + (int64_t)g * 4;
                int r0, r1, q0, q1;
                row_range<T>(bnd[2], bnd[3], y0, nrows, r0, r1);
                row_range<T>(bnd[0], bnd[1], x0, ncols, q0, q1);
                if (q0 >= q1) continue;  // no pixel centre of the tile in the box: nothing to do
                // the lane chunks [h0, h1) meeting the box's columns (lanes outside it get alpha < 1/255)
                const int h0 = (q0 - x0) / HL, h1 = (q1 - 1 - x0) / HL + 1;
                const T o = p[P_O], c0 = p[P_R], c1 = p[P_G], c2 = p[P_B];
                [[maybe_unused]] T dpl = T(0);  // plane distance d of this Gaussian
                if constexpr (PL) dpl = PD[g];
                const int kk = k - beg;
                for (int y = r0; y < r1; ++y) {
                    const T py = T(y) + T(0.5);
                    const T ry = (py - cy) / fy;
                    const int base = (y - y0) * TS;
                    int nstop = 0;
                    // one pixel; run as a 16-lane loop when both chunks meet the box, else as one 8-lane
                    // chunk (constant trip counts: straight vector code, no remainder loops)
                    auto lane = [&](const int lx) __attribute__((always_inline)) -> int {
                        const int i = base + lx;
                        const T px = T(x0 + lx) + T(0.5);
                        const T rx = rxs[lx];
                        T invr = T(1);
                        if constexpr (K == K_RADE && GEOM) invr = invrs[i];
                        Eval<K, T> e;
                        eval_lane<K, T>(e, p, px, py, rx, ry, invr, nearz, surfel_k, GEOM);
                        const T al = std::min(T(0.99), o * e.G);
                        const bool v = act[i] > T(0) && e.ok && al >= T(1.0 / 255.0);
                        const T Ti = Tr[i];
                        const T Tn = Ti * (T(1) - al);
                        const bool stop = v && Tn < T(1e-4);
                        const bool bl = v && !stop;
                        const T w = bsel<T>(bl, al * Ti, T(0));
                        cr[i] += w * c0;  // also when rgb is not requested (not written back): no branch
                        cg[i] += w * c1;
                        cb[i] += w * c2;
                        wa[i] += w;
                        Tr[i] = bsel<T>(bl, Tn, Ti);
                        lastk[i] = bsel<int32_t>(bl, kk + 1, lastk[i]);
                        act[i] = bsel<T>(stop, T(0), act[i]);
                        const int nst = stop ? 1 : 0;
                        if constexpr (GEOM) {
                            dep[i] += w * e.z;
                            const bool mm = bl && Ti > T(0.5);
                            medi[i] = bsel<int32_t>(mm, kk, medi[i]);
                            med[i] = bsel<T>(mm, e.z, med[i]);
                            n0[i] += w * e.n0;
                            n1[i] += w * e.n1;
                            n2[i] += w * e.n2;
                            if constexpr (PL) pl[i] += w * dpl;  // Σ w d
                            if constexpr (DIST) {
                                const bool zp = e.z > T(0);
                                const T mz = bsel<T>(zp, mapm<T>(bsel<T>(zp, e.z, T(1)), nearz, farz), T(0)) - m0;
                                m1[i] += w * mz;
                                m2[i] += w * mz * mz;
                            }
                        }
                        return nst;
                    };
                    if (h1 - h0 == 2) {
                        pairs += TS;
#pragma omp simd reduction(+ : nstop)
                        for (int lx = 0; lx < TS; ++lx) nstop += lane(lx);
                    } else {
                        pairs += HL;
                        const int lb = h0 * HL;
#pragma omp simd reduction(+ : nstop)
                        for (int l = 0; l < HL; ++l) nstop += lane(lb + l);
                    }
                    ndone += nstop;
                }
            }
            // write back
            for (int ly = 0; ly < nrows; ++ly) {
                for (int lx = 0; lx < ncols; ++lx) {
                    const int i = ly * TS + lx;
                    const int64_t pix = (int64_t)(y0 + ly) * W + (x0 + lx);
                    o_T[pix] = Tr[i];
                    A.last[pix] = lastk[i];
                    o_alpha[pix] = wa[i];  // Σ w (= 1 − T, without the cancellation at small alpha)
                    if (w_rgb) {
                        o_rgb[pix * 3 + 0] = cr[i];
                        o_rgb[pix * 3 + 1] = cg[i];
                        o_rgb[pix * 3 + 2] = cb[i];
                    }
                    if constexpr (GEOM) {
                        if (w_depth) o_depth[pix] = dep[i];
                        if (w_med) {
                            o_med[pix] = med[i];
                            A.median_idx[pix] = medi[i];
                        }
                        if (w_nrm) {
                            o_nrm[pix * 3 + 0] = n0[i];
                            o_nrm[pix * 3 + 1] = n1[i];
                            o_nrm[pix * 3 + 2] = n2[i];
                        }
                        if constexpr (DIST) {  // MODE 2 is chosen exactly when the distortion is wanted
                            const T Wt = T(1) - Tr[i];
                            o_dist[pix] = std::max(Wt * m2[i] - m1[i] * m1[i], T(0));
                            o_M1[pix] = m1[i];
                            o_M2[pix] = m2[i];
                        }
                        if constexpr (PL) o_pl[pix] = pl[i];
                    }
                }
            }
        }
    }
    A.pairs = pairs;
}

// ---------------------------------------------------------------------------------------------
// Backward
// ---------------------------------------------------------------------------------------------
// slots: 0..NPK-1 = payload gradient, NPK = absgrad, NPK+1..NPK+2 = proxy (raymax), NPK+3 = dL/dd of the
// plane distance (PL only: g_plane given). The plane channel enters like a colour channel: ψ += g_plane·d
// (so the suffix B carries it into dL/dα of the Gaussians in front) and dL/dd = Σ_pixels w·g_plane.

template <int K, typename T, int MODE, bool PL>
void backward_impl(GsArgs& A) {
    constexpr bool GEOM = MODE >= 1, DIST = MODE == 2;
    static_assert(GEOM || !PL, "the plane distance is a geometry output");
    constexpr int NPK = NP<K>::v;
    constexpr int NS = NPK + (PL ? 4 : 3);  // the slots above (lane accumulators, thread buffer rows)
    const int W = (int)A.width, H = (int)A.height, TX = (int)A.tiles_x, TY = (int)A.tiles_y;
    const int64_t N = A.n_gauss;
    const T* __restrict P = (const T*)A.params;
    const T* __restrict BND = (const T*)A.bounds;
    const T* __restrict DK = (const T*)A.depth_key;
    const T fx = (T)A.fx, fy = (T)A.fy, cx = (T)A.cx, cy = (T)A.cy, nearz = (T)A.near_z, farz = (T)A.far_z,
            surfel_k = (T)A.surfel_k;
    const T* g_rgb = (const T*)A.g_rgb;
    const T* g_alpha = (const T*)A.g_alpha;
    const T* g_depth = GEOM ? (const T*)A.g_depth : nullptr;
    const T* g_med = GEOM ? (const T*)A.g_median : nullptr;
    const T* g_nrm = GEOM ? (const T*)A.g_normal : nullptr;
    const T* g_dist = DIST ? (const T*)A.g_dist : nullptr;
    const T* g_pl = PL ? (const T*)A.g_plane : nullptr;
    const T* __restrict PD = (const T*)A.plane_d;
    const bool b_rgb = g_rgb != nullptr, b_alpha = g_alpha != nullptr, b_depth = g_depth != nullptr,
               b_med = g_med != nullptr, b_nrm = g_nrm != nullptr, b_dist = g_dist != nullptr;
    const bool detach = A.detach_dist;
    const T* sT = (const T*)A.T_final;
    const T* sM1 = (const T*)A.M1;
    const T* sM2 = (const T*)A.M2;
    const T halfW = T(0.5) * W, halfH = T(0.5) * H;
    const int nthreads = std::max(1, (int)A.nthreads);
    const int ntiles = TX * TY;

    // per-thread accumulation buffers (thread 0 writes straight into the outputs)
    std::vector<std::vector<T>> extra(nthreads > 1 ? nthreads - 1 : 0);
    int64_t pairs = 0;

#pragma omp parallel num_threads(nthreads) reduction(+ : pairs)
    {
        FTZGuard ftz;
        const int tid = omp_get_thread_num();
        T* gp;
        T* ga;
        T* gx;
        [[maybe_unused]] T* gpl;  // dL/dd (PL)
        if (tid == 0) {
            gp = (T*)A.grad_params;
            ga = (T*)A.absgrad;
            gx = (T*)A.proxy;
            gpl = (T*)A.grad_plane;
        } else {
            auto& buf = extra[tid - 1];
            buf.assign((size_t)N * NS, T(0));
            gp = buf.data();
            ga = gp + (size_t)N * NPK;
            gx = ga + N;
            gpl = gx + 2 * N;  // only with PL (the buffer has N more rows)
        }
        alignas(64) T Tr[TP], Bb[TP], ga0[TP], gc0[TP], gc1[TP], gc2[TP], gD[TP], gm[TP], gN0[TP], gN1[TP], gN2[TP];
        alignas(64) T gd[TP], gdp[TP], Wt[TP], M1[TP], M2[TP];
        alignas(64) T gP[PL ? TP : 1];
        alignas(64) int32_t lastk[TP], medi[TP];
        alignas(64) T rxs[TS];
        alignas(64) T invrs[K == K_RADE && GEOM ? TP : 1];
        alignas(64) T acc[NS][TS];
        alignas(64) T proxy_dal[TS];
#pragma omp for schedule(static, 1)
        for (int tile = 0; tile < ntiles; ++tile) {
            const int tx = tile % TX, ty = tile / TX;
            const int x0 = tx * TS, y0 = ty * TS;
            const int ncols = std::min(TS, W - x0), nrows = std::min(TS, H - y0);
            int maxlast = 0;
            for (int i = 0; i < TP; ++i) {
                const int ly = i / TS, lx = i % TS;
                const bool in = ly < nrows && lx < ncols;
                const int64_t pix = in ? (int64_t)(y0 + ly) * W + (x0 + lx) : 0;
                lastk[i] = in ? A.last[pix] : 0;
                maxlast = std::max(maxlast, lastk[i]);
                const T tf = in ? sT[pix] : T(1);
                Tr[i] = tf;
                Bb[i] = T(0);
                ga0[i] = (in && b_alpha) ? g_alpha[pix] : T(0);
                gc0[i] = (in && b_rgb) ? g_rgb[pix * 3 + 0] : T(0);
                gc1[i] = (in && b_rgb) ? g_rgb[pix * 3 + 1] : T(0);
                gc2[i] = (in && b_rgb) ? g_rgb[pix * 3 + 2] : T(0);
                if constexpr (GEOM) {
                    gD[i] = (in && b_depth) ? g_depth[pix] : T(0);
                    gm[i] = (in && b_med) ? g_med[pix] : T(0);
                    medi[i] = (in && b_med) ? A.median_idx[pix] : -1;
                    gN0[i] = (in && b_nrm) ? g_nrm[pix * 3 + 0] : T(0);
                    gN1[i] = (in && b_nrm) ? g_nrm[pix * 3 + 1] : T(0);
                    gN2[i] = (in && b_nrm) ? g_nrm[pix * 3 + 2] : T(0);
                    gd[i] = (in && b_dist) ? g_dist[pix] : T(0);
                    gdp[i] = detach ? T(0) : gd[i];  // weight of the distortion term in psi (0: detached)
                    Wt[i] = T(1) - tf;
                    M1[i] = (in && b_dist) ? sM1[pix] : T(0);
                    M2[i] = (in && b_dist) ? sM2[pix] : T(0);
                }
                if constexpr (PL) gP[i] = in ? g_pl[pix] : T(0);
            }
            if (maxlast == 0) continue;
            for (int lx = 0; lx < TS; ++lx) rxs[lx] = (T(x0 + lx) + T(0.5) - cx) / fx;
            if constexpr (K == K_RADE && GEOM) fill_invr<T>(invrs, rxs, y0, nrows, cy, fy);
            const int beg = A.tile_offsets[tile];
            T m0 = T(0);
            if (DIST) m0 = mapm<T>(DK[A.tile_list[beg]], nearz, farz);
            for (int kk = maxlast - 1; kk >= 0; --kk) {
                if (kk >= PF) {
                    const int gq = A.tile_list[beg + kk - PF];
                    prefetch_gauss<NPK, T>(P, BND, gq);
                    // and its gradient rows (read-modify-write after the lanes; random access into N)
                    const char* q = (const char*)(gp + (int64_t)gq * NPK);
                    __builtin_prefetch(q, 1, 1);
                    __builtin_prefetch(q + NPK * sizeof(T) - 1, 1, 1);
                    __builtin_prefetch(ga + gq, 1, 1);
                    if constexpr (PL) {
                        __builtin_prefetch(PD + gq, 0, 1);
                        __builtin_prefetch(gpl + gq, 1, 1);
                    }
                }
                const int g = A.tile_list[beg + kk];
                const T* __restrict p = P + (int64_t)g * NPK;
                const T* bnd = BND + (int64_t)g * 4;
                int r0, r1, q0, q1;
                row_range<T>(bnd[2], bnd[3], y0, nrows, r0, r1);
                row_range<T>(bnd[0], bnd[1], x0, ncols, q0, q1);
                if (r0 >= r1 || q0 >= q1) continue;
                // lanes [l0, l1): the chunks meeting the box's columns (the others would only add zeros)
                const int h0 = (q0 - x0) / HL, h1 = (q1 - 1 - x0) / HL + 1;
                const int l0 = h0 * HL, l1 = h1 * HL;
                if (l1 - l0 == TS) {  // constant trip counts: vector stores, no memset calls
                    for (int s = 0; s < NS; ++s)
                        for (int lx = 0; lx < TS; ++lx) acc[s][lx] = T(0);
                } else {
                    for (int s = 0; s < NS; ++s)
                        for (int l = 0; l < HL; ++l) acc[s][l0 + l] = T(0);
                }
                const T o = p[P_O], c0 = p[P_R], c1 = p[P_G], c2 = p[P_B];
                [[maybe_unused]] T dpl = T(0);  // plane distance d of this Gaussian
                if constexpr (PL) dpl = PD[g];
                int nvalid = 0;
                for (int y = r0; y < r1; ++y) {
                    const T py = T(y) + T(0.5);
                    const T ry = (py - cy) / fy;
                    const int base = (y - y0) * TS;
                    // one pixel (16-lane loop or one 8-lane chunk, as in the forward); returns v
                    auto lane = [&](const int lx) __attribute__((always_inline)) -> int {
                        const int i = base + lx;
                        const T px = T(x0 + lx) + T(0.5);
                        const T rx = rxs[lx];
                        T invr = T(1);
                        if constexpr (K == K_RADE && GEOM) invr = invrs[i];
                        Eval<K, T> e;
                        eval_lane<K, T>(e, p, px, py, rx, ry, invr, nearz, surfel_k, GEOM);
                        const T oG = o * e.G;
                        const T al = std::min(T(0.99), oG);
                        const bool v = kk < lastk[i] && e.ok && al >= T(1.0 / 255.0);
                        const int nv = v ? 1 : 0;
                        const T ia = T(1) / (T(1) - al);
                        const T Ti = Tr[i] * ia;
                        const T w = al * Ti;
                        T psi = ga0[i] + gc0[i] * c0 + gc1[i] * c1 + gc2[i] * c2;
                        T mz = T(0), dmz = T(0);
                        if constexpr (GEOM) {
                            psi += gD[i] * e.z + gN0[i] * e.n0 + gN1[i] * e.n1 + gN2[i] * e.n2;
                            if constexpr (PL) psi += gP[i] * dpl;
                            if constexpr (DIST) {
                                const bool zp = e.z > T(0);
                                const T zz = bsel<T>(zp, e.z, T(1));
                                mz = bsel<T>(zp, mapm<T>(zz, nearz, farz), T(0)) - m0;
                                dmz = bsel<T>(zp, dmapm<T>(zz, nearz, farz), T(0));
                                // gdp = 0 when detached (a per-lane select: an invariant one does not vectorise)
                                const T psd = psi + gdp[i] * (M2[i] + Wt[i] * mz * mz - T(2) * M1[i] * mz);
                                psi = bsel<T>(gdp[i] != T(0), psd, psi);
                            }
                        }
                        const T dal = Ti * psi - Bb[i] * ia;
                        Bb[i] = bsel<T>(v, Bb[i] + w * psi, Bb[i]);
                        Tr[i] = bsel<T>(v, Ti, Tr[i]);
                        const bool vg = v && oG <= T(0.99);
                        const T dG = bsel<T>(vg, o * dal, T(0));
                        acc[P_O][lx] += bsel<T>(vg, e.G * dal, T(0));
                        const T wv = bsel<T>(v, w, T(0));
                        acc[P_R][lx] += wv * gc0[i];
                        acc[P_G][lx] += wv * gc1[i];
                        acc[P_B][lx] += wv * gc2[i];
                        T dz = T(0), dn0 = T(0), dn1 = T(0), dn2 = T(0);
                        if constexpr (GEOM) {
                            dz = wv * gD[i] + bsel<T>(v && kk == medi[i], gm[i], T(0));
                            if constexpr (DIST) dz += wv * gd[i] * T(2) * (Wt[i] * mz - M1[i]) * dmz;
                            dn0 = wv * gN0[i];
                            dn1 = wv * gN1[i];
                            dn2 = wv * gN2[i];
                            if constexpr (PL) acc[NPK + 3][lx] += wv * gP[i];  // dL/dd = Σ w g_plane
                        }
                        T gmx = T(0), gmy = T(0);
                        if constexpr (K == K_EWA || K == K_RADE) {
                            const T gG = dG * e.G;
                            gmx = gG * (p[P_CA] * e.dx + p[P_CB] * e.dy);
                            gmy = gG * (p[P_CB] * e.dx + p[P_CC] * e.dy);
                            acc[P_CA][lx] += T(-0.5) * gG * e.dx * e.dx;
                            acc[P_CB][lx] += -gG * e.dx * e.dy;
                            acc[P_CC][lx] += T(-0.5) * gG * e.dy * e.dy;
                            if constexpr (K == K_EWA) {
                                acc[P_X][lx] += dz;
                                acc[P_X + 1][lx] += dn0;
                                acc[P_X + 2][lx] += dn1;
                                acc[P_X + 3][lx] += dn2;
                            } else {
                                const T dzi = dz * invr;
                                acc[P_X][lx] += dzi;
                                acc[P_X + 1][lx] += dzi * e.dx;
                                acc[P_X + 2][lx] += dzi * e.dy;
                                gmx -= dzi * p[P_X + 1];
                                gmy -= dzi * p[P_X + 2];
                                acc[P_X + 3][lx] += dn0;
                                acc[P_X + 4][lx] += dn1;
                                acc[P_X + 5][lx] += dn2;
                            }
                            acc[P_MX][lx] += gmx;
                            acc[P_MY][lx] += gmy;
                            acc[NPK][lx] += std::fabs(gmx) * halfW + std::fabs(gmy) * halfH;
                        } else if constexpr (K == K_RAYMAX) {
                            const T* a = p + P_X;
                            const T dq = T(-0.5) * e.G * dG;
                            const T dnum = dq * a[12] * e.rAr_inv;
                            acc[P_X + 12][lx] += dq * e.num * e.rAr_inv;
                            const T drAr = -(dq * e.q + dz * e.t) * e.rAr_inv;
                            const T dbr = dz * e.rAr_inv;
                            T gA0 = T(0), gA1 = T(0), gA2 = T(0);
                            if constexpr (GEOM) {
                                // n = -Ar/|Ar|: dL/dAr = -(I - n nᵀ) dn / |Ar|
                                const T nd = e.n0 * dn0 + e.n1 * dn1 + e.n2 * dn2;
                                gA0 = -(dn0 - e.n0 * nd) * e.nrm_inv;
                                gA1 = -(dn1 - e.n1 * nd) * e.nrm_inv;
                                gA2 = -(dn2 - e.n2 * nd) * e.nrm_inv;
                            }
                            acc[P_X + 0][lx] += drAr * rx * rx + gA0 * rx;
                            acc[P_X + 1][lx] += drAr * T(2) * rx * ry + gA0 * ry + gA1 * rx;
                            acc[P_X + 2][lx] += drAr * T(2) * rx + gA0 + gA2 * rx;
                            acc[P_X + 3][lx] += drAr * ry * ry + gA1 * ry;
                            acc[P_X + 4][lx] += drAr * T(2) * ry + gA1 + gA2 * ry;
                            acc[P_X + 5][lx] += drAr + gA2;
                            acc[P_X + 6][lx] += dbr * rx;
                            acc[P_X + 7][lx] += dbr * ry;
                            acc[P_X + 8][lx] += dbr;
                            acc[P_X + 9][lx] += dnum * e.Dx * e.Dx;
                            acc[P_X + 10][lx] += dnum * T(2) * e.Dx * e.Dy;
                            acc[P_X + 11][lx] += dnum * e.Dy * e.Dy;
                            acc[P_X + 13][lx] -= dnum * T(2) * (a[9] * e.Dx + a[10] * e.Dy);
                            acc[P_X + 14][lx] -= dnum * T(2) * (a[10] * e.Dx + a[11] * e.Dy);
                            // GOF densification proxy: computed in a second lane loop below (keeps this one vectorisable)
                            proxy_dal[lx] = dG;  // = vg ? o·dal : 0
                        } else {  // surfel
                            const T drho = T(-0.5) * e.G * dG;
                            T gs0 = bsel<T>(e.branch3d, drho * T(2) * e.s0, T(0));
                            T gs1 = bsel<T>(e.branch3d, drho * T(2) * e.s1, T(0));
                            gmx = bsel<T>(e.branch3d, T(0), drho * T(2) * surfel_k * e.dx);
                            gmy = bsel<T>(e.branch3d, T(0), drho * T(2) * surfel_k * e.dy);
                            const T vm = bsel<T>(v, T(1), T(0));
                            gs0 *= vm;
                            gs1 *= vm;
                            const T dt = dz + gs0 * e.k0 + gs1 * e.l0;
                            const T dnr = -dt * e.t * e.ip;
                            acc[P_X + 0][lx] += dnr * rx + dn0;
                            acc[P_X + 1][lx] += dnr * ry + dn1;
                            acc[P_X + 2][lx] += dnr + dn2;
                            acc[P_X + 3][lx] += dt * e.ip;
                            const T tu = gs0 * e.t, tv = gs1 * e.t;
                            acc[P_X + 4][lx] += tu * rx;
                            acc[P_X + 5][lx] += tu * ry;
                            acc[P_X + 6][lx] += tu;
                            acc[P_X + 7][lx] -= gs0;
                            acc[P_X + 8][lx] += tv * rx;
                            acc[P_X + 9][lx] += tv * ry;
                            acc[P_X + 10][lx] += tv;
                            acc[P_X + 11][lx] -= gs1;
                            gmx *= vm;
                            gmy *= vm;
                            acc[P_MX][lx] += gmx;
                            acc[P_MY][lx] += gmy;
                            acc[NPK][lx] += std::fabs(gmx) * halfW + std::fabs(gmy) * halfH;
                        }
                        return nv;
                    };
                    // GOF densification proxy (raymax): a second lane loop, keeps the first one vectorisable
                    auto proxy_lane = [&](const int lx) __attribute__((always_inline)) {
                        const T px = T(x0 + lx) + T(0.5);
                        const T ddx = px - p[P_MX], ddy = py - p[P_MY];
                        const T pw = T(-0.5) * (p[P_CA] * ddx * ddx + p[P_CC] * ddy * ddy) - p[P_CB] * ddx * ddy;
                        const T gg = proxy_dal[lx] * fexp<T>(std::max(std::min(pw, T(0)), T(-30)));
                        const T gmx = gg * (p[P_CA] * ddx + p[P_CB] * ddy);
                        const T gmy = gg * (p[P_CB] * ddx + p[P_CC] * ddy);
                        acc[NPK + 1][lx] += gmx;
                        acc[NPK + 2][lx] += gmy;
                        acc[NPK][lx] += std::fabs(gmx) * halfW + std::fabs(gmy) * halfH;
                    };
                    if (h1 - h0 == 2) {
                        pairs += TS;
#pragma omp simd reduction(+ : nvalid)
                        for (int lx = 0; lx < TS; ++lx) nvalid += lane(lx);
                        if constexpr (K == K_RAYMAX) {
#pragma omp simd
                            for (int lx = 0; lx < TS; ++lx) proxy_lane(lx);
                        }
                    } else {
                        pairs += HL;
                        const int lb = h0 * HL;
#pragma omp simd reduction(+ : nvalid)
                        for (int l = 0; l < HL; ++l) nvalid += lane(lb + l);
                        if constexpr (K == K_RAYMAX) {
#pragma omp simd
                            for (int l = 0; l < HL; ++l) proxy_lane(lb + l);
                        }
                    }
                }
                if (nvalid == 0) continue;
                T* dst = gp + (int64_t)g * NPK;
                for (int s = 0; s < NPK; ++s) {
                    T sum = T(0);
                    for (int lx = l0; lx < l1; ++lx) sum += acc[s][lx];
                    dst[s] += sum;
                }
                T sa = T(0), sx = T(0), sy = T(0);
                for (int lx = l0; lx < l1; ++lx) {
                    sa += acc[NPK][lx];
                    sx += acc[NPK + 1][lx];
                    sy += acc[NPK + 2][lx];
                }
                ga[g] += sa;
                if constexpr (K == K_RAYMAX) {
                    gx[2 * g] += sx;
                    gx[2 * g + 1] += sy;
                }
                if constexpr (PL) {
                    T sp = T(0);
                    for (int lx = l0; lx < l1; ++lx) sp += acc[NPK + 3][lx];
                    gpl[g] += sp;
                }
            }
        }
    }
    // reduce per-thread buffers
    if (!extra.empty()) {
        T* gp = (T*)A.grad_params;
        T* ga = (T*)A.absgrad;
        T* gx = (T*)A.proxy;
        const int64_t tot = N * NPK;
#pragma omp parallel for num_threads(nthreads) schedule(static)
        for (int64_t j = 0; j < tot; ++j) {
            T s = T(0);
            for (auto& b : extra) s += b[j];
            gp[j] += s;
        }
        for (auto& b : extra) {
            const T* bb = b.data() + N * NPK;
            for (int64_t j = 0; j < N; ++j) ga[j] += bb[j];
            if (K == K_RAYMAX)
                for (int64_t j = 0; j < 2 * N; ++j) gx[j] += bb[N + j];
            if (PL) {
                T* gpl = (T*)A.grad_plane;
                for (int64_t j = 0; j < N; ++j) gpl[j] += bb[3 * N + j];
            }
        }
    }
    A.pairs = pairs;
}

template <int K, typename T>
int dispatch_geom(GsArgs& A, bool fwd) {
    const bool plane = fwd ? A.want_plane != 0 : A.g_plane != nullptr;  // the plane distance runs in GEOM mode
    const bool geom = plane || (fwd ? (A.want_depth || A.want_median || A.want_normal || A.want_dist)
                                    : (A.g_depth || A.g_median || A.g_normal || A.g_dist));
    const bool dist = fwd ? A.want_dist : A.g_dist != nullptr;
    const int mode = !geom ? 0 : dist ? 2 : 1;
    if (fwd) {
        if (mode == 0) forward_impl<K, T, 0, false>(A);
        else if (mode == 1) plane ? forward_impl<K, T, 1, true>(A) : forward_impl<K, T, 1, false>(A);
        else plane ? forward_impl<K, T, 2, true>(A) : forward_impl<K, T, 2, false>(A);
    } else {
        if (mode == 0) backward_impl<K, T, 0, false>(A);
        else if (mode == 1) plane ? backward_impl<K, T, 1, true>(A) : backward_impl<K, T, 1, false>(A);
        else plane ? backward_impl<K, T, 2, true>(A) : backward_impl<K, T, 2, false>(A);
    }
    return 0;
}

template <typename T>
int dispatch_kernel(GsArgs& A, bool fwd) {
    switch (A.kernel) {
        case K_EWA: return dispatch_geom<K_EWA, T>(A, fwd);
        case K_RADE: return dispatch_geom<K_RADE, T>(A, fwd);
        case K_RAYMAX: return dispatch_geom<K_RAYMAX, T>(A, fwd);
        case K_SURFEL: return dispatch_geom<K_SURFEL, T>(A, fwd);
        default: return -1;
    }
}

// Counting sort of M depth-ordered entries into per-tile lists, shared by gs_bin and gs_bin_sorted:
// per-thread tile counts, a prefix sum into ``offsets`` (ntiles + 1), then each thread fills the tiles
// of its own band of tile rows (bands hold about equal pair counts), reading the entries in depth
// order so every tile list stays front to back. ``rect_of(j)`` gives entry j's x0 x1 y0 y1 (exclusive
// ends), ``id_of(j)`` its Gaussian id. Returns the pair count, or -1 if it exceeds ``capacity``.
template <class RectOf, class IdOf>
int64_t bin_entries(int64_t M, RectOf rect_of, IdOf id_of, int64_t tiles_x, int64_t tiles_y, int32_t* offsets,
                    int32_t* list, int64_t capacity, int64_t nthreads) {
    const int64_t ntiles = tiles_x * tiles_y;
    const int nt = (int)std::max<int64_t>(1, nthreads);
    std::vector<std::vector<int32_t>> counts(nt, std::vector<int32_t>(ntiles, 0));
#pragma omp parallel num_threads(nt)
    {
        auto& c = counts[omp_get_thread_num()];
#pragma omp for schedule(static)
        for (int64_t j = 0; j < M; ++j) {
            const int32_t* r = rect_of(j);
            for (int y = r[2]; y < r[3]; ++y)
                for (int x = r[0]; x < r[1]; ++x) c[y * tiles_x + x]++;
        }
    }
    std::vector<int32_t> cursor(ntiles + 1, 0);
    for (int64_t t = 0; t < ntiles; ++t) {
        int32_t tot = 0;
        for (int k = 0; k < nt; ++k) tot += counts[k][t];
        cursor[t + 1] = cursor[t] + tot;
    }
    if (cursor[ntiles] > capacity) return -1;
    std::memcpy(offsets, cursor.data(), sizeof(int32_t) * (ntiles + 1));
    std::vector<int> band(nt + 1, (int)tiles_y);  // rows [band[k], band[k+1]) belong to thread k
    band[0] = 0;
    {
        const int64_t total = cursor[ntiles];
        int k = 1;
        for (int y = 0; y < tiles_y && k < nt; ++y)
            while (k < nt && cursor[(y + 1) * tiles_x] >= total * k / nt) band[k++] = y + 1;
    }
#pragma omp parallel for num_threads(nt) schedule(static, 1)
    for (int k = 0; k < nt; ++k) {
        const int ylo = band[k], yhi = band[k + 1];
        if (ylo >= yhi) continue;
        int32_t* cur = cursor.data();
        for (int64_t j = 0; j < M; ++j) {
            const int32_t* r = rect_of(j);
            const int y0 = std::max<int>(r[2], ylo), y1 = std::min<int>(r[3], yhi);
            const int32_t g = id_of(j);
            for (int y = y0; y < y1; ++y) {
                int32_t* c = cur + y * tiles_x;
                for (int x = r[0]; x < r[1]; ++x) list[c[x]++] = g;
            }
        }
    }
    return offsets[ntiles];
}

}  // namespace

extern "C" {

int gs_abi_version() { return 1; }

int gs_forward(GsArgs* A) {
    if (A->n_params != (A->kernel == K_EWA ? 13 : A->kernel == K_RADE ? 15 : A->kernel == K_RAYMAX ? 24 : 21)) return -2;
    return A->dtype == 0 ? dispatch_kernel<float>(*A, true) : dispatch_kernel<double>(*A, true);
}

int gs_backward(GsArgs* A) {
    return A->dtype == 0 ? dispatch_kernel<float>(*A, false) : dispatch_kernel<double>(*A, false);
}

// gs_bin: order = M visible Gaussian ids sorted by (depth, id); rect: (N, 4) per Gaussian.
int64_t gs_bin(int64_t M, const int64_t* order, const int32_t* rect, int64_t tiles_x, int64_t tiles_y,
               int32_t* offsets, int32_t* list, int64_t capacity, int64_t nthreads) {
    return bin_entries(
        M, [&](int64_t j) { return rect + order[j] * 4; }, [&](int64_t j) { return (int32_t)order[j]; },
        tiles_x, tiles_y, offsets, list, capacity, nthreads);
}


// ---------------------------------------------------------------------------------------------
// Depth order and binning without random access into per-Gaussian arrays.
// ---------------------------------------------------------------------------------------------
}  // extern "C"

namespace {

inline uint32_t sort_key(float x) {
    uint32_t b = __builtin_bit_cast(uint32_t, x);
    if (b == 0x80000000u) b = 0;  // -0 == +0 (ties by index, as torch.sort)
    return (b & 0x80000000u) ? ~b : (b | 0x80000000u);
}
inline uint64_t sort_key(double x) {
    uint64_t b = __builtin_bit_cast(uint64_t, x);
    if (b == 0x8000000000000000ull) b = 0;
    return (b & 0x8000000000000000ull) ? ~b : (b | 0x8000000000000000ull);
}

// LSD radix sort (stable) of the visible Gaussians by depth; ids ascending on input, so ties keep index order.
template <typename T, typename U>
int64_t depth_order_impl(int64_t N, const uint8_t* visible, const T* depth, const int32_t* rect, int32_t* order,
                         int32_t* rect_sorted) {
    constexpr int BITS = 11, NB = 1 << BITS, PASSES = (int)(sizeof(U) * 8 + BITS - 1) / BITS;
    std::vector<U> key, key2;
    std::vector<int32_t> id, id2;
    key.reserve(N);
    id.reserve(N);
    for (int64_t i = 0; i < N; ++i)
        if (visible[i]) {
            key.push_back(sort_key(depth[i]));
            id.push_back((int32_t)i);
        }
    const int64_t M = (int64_t)key.size();
    key2.resize(M);
    id2.resize(M);
    std::vector<int64_t> hist((size_t)PASSES * NB, 0);
    for (int64_t j = 0; j < M; ++j) {
        const U k = key[j];
        for (int p = 0; p < PASSES; ++p) hist[(size_t)p * NB + ((k >> (p * BITS)) & (NB - 1))]++;
    }
    for (int p = 0; p < PASSES; ++p) {
        int64_t* h = hist.data() + (size_t)p * NB;
        bool trivial = false;
        for (int b = 0; b < NB; ++b)
            if (h[b] == M) trivial = true;
        if (trivial) continue;  // every key has the same digit here
        int64_t run = 0;
        for (int b = 0; b < NB; ++b) {
            const int64_t c = h[b];
            h[b] = run;
            run += c;
        }
        for (int64_t j = 0; j < M; ++j) {
            const int64_t d = h[(key[j] >> (p * BITS)) & (NB - 1)]++;
            key2[d] = key[j];
            id2[d] = id[j];
        }
        key.swap(key2);
        id.swap(id2);
    }
    for (int64_t j = 0; j < M; ++j) {
        if (j + 64 < M) __builtin_prefetch(rect + (int64_t)id[j + 64] * 4, 0, 3);
        order[j] = id[j];
        std::memcpy(rect_sorted + 4 * j, rect + (int64_t)id[j] * 4, 4 * sizeof(int32_t));
    }
    return M;
}

}  // namespace

extern "C" {

// Visible Gaussian ids sorted by (depth, id) into `order` (int32, room for N) and their tile rectangles
// in that order into `rect_sorted` (M, 4). Returns M; `pairs_out` = Σ rectangle areas (tile pairs).
int64_t gs_depth_order(int64_t N, const uint8_t* visible, const void* depth, int64_t dtype, const int32_t* rect,
                       int32_t* order, int32_t* rect_sorted, int64_t* pairs_out) {
    const int64_t M = dtype == 0 ? depth_order_impl<float, uint32_t>(N, visible, (const float*)depth, rect, order, rect_sorted)
                                 : depth_order_impl<double, uint64_t>(N, visible, (const double*)depth, rect, order, rect_sorted);
    int64_t pairs = 0;
    for (int64_t j = 0; j < M; ++j) {
        const int32_t* r = rect_sorted + 4 * j;
        pairs += (int64_t)(r[1] - r[0]) * (int64_t)(r[3] - r[2]);
    }
    *pairs_out = pairs;
    return M;
}

// gs_bin on the output of gs_depth_order: rs holds the rectangles already in depth order, so every
// read is sequential.
int64_t gs_bin_sorted(int64_t M, const int32_t* order, const int32_t* rs, int64_t tiles_x, int64_t tiles_y,
                      int32_t* offsets, int32_t* list, int64_t capacity, int64_t nthreads) {
    return bin_entries(
        M, [&](int64_t j) { return rs + 4 * j; }, [&](int64_t j) { return order[j]; },
        tiles_x, tiles_y, offsets, list, capacity, nthreads);
}

}  // extern "C"

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
