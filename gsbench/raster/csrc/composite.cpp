// gsbench tile rasterizer: front-to-back compositing and its reverse pass (the tile lists come from
// sort_bin.cpp or bin_exact.cpp).
//
// Plain C ABI (called through ctypes; no torch headers).
// Per-Gaussian payload layout: see gsbench/raster/payload.py. Pixel (i, j) is evaluated at
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
//
// The list prefetch reads a clamped index, not `if (k + PF < end)`: with that branch GCC 12 splits the
// list loop in two (-fsplit-loops, on at -O3) and its copy for the last PF entries keeps the lane loops
// scalar. Those are the tile's front-most Gaussians, often the largest on screen, so the scalar copy
// took about 30% of the backward (experiments/papers_size/README.md, "The scalar copy of the list loop").

#include "raster_common.h"

namespace {

// The forward stops walking a tile's list once every pixel has stopped (T < 1e-4), checked every DONE_EVERY
// entries: counting the stopped lanes in every row cost a horizontal reduction per row, about a fifth of the
// forward. The entries walked after the last pixel stopped blend nothing (their lanes are inactive).
constexpr int DONE_EVERY = 16;

template <typename T>
inline bool all_stopped(const T* __restrict act) {
    int any = 0;
#pragma omp simd reduction(| : any)
    for (int i = 0; i < TP; ++i) any |= act[i] > T(0) ? 1 : 0;
    return any == 0;
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
            const int beg = A.tile_offsets[tile], end = A.tile_offsets[tile + 1];
            T m0 = T(0);
            if (DIST && end > beg) m0 = mapm<T>(DK[A.tile_list[beg]], nearz, farz);
            for (int k = beg; k < end; ++k) {
                if ((k - beg) % DONE_EVERY == DONE_EVERY - 1 && all_stopped<T>(act)) break;
                {  // branch-free (clamped) index: a branch on k here lets GCC split the loop (module header)
                    const int gq = A.tile_list[std::min(k + PF, end - 1)];
                    prefetch_gauss<NPK, T>(P, BND, gq);
                    if constexpr (PL) __builtin_prefetch(PD + gq, 0, 1);
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
                    // one pixel; run as a 16-lane loop when both chunks meet the box, else as one 8-lane
                    // chunk (constant trip counts: straight vector code, no remainder loops)
                    auto lane = [&](const int lx) __attribute__((always_inline)) {
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
                    };
                    if (h1 - h0 == 2) {
                        pairs += TS;
#pragma omp simd
                        for (int lx = 0; lx < TS; ++lx) lane(lx);
                    } else {
                        pairs += HL;
                        const int lb = h0 * HL;
#pragma omp simd
                        for (int l = 0; l < HL; ++l) lane(lb + l);
                    }
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
        alignas(64) int32_t valid[TS];  // lane blended this Gaussian in some row (reduced once per entry)
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
                {  // branch-free (clamped) index, as in the forward
                    const int gq = A.tile_list[beg + std::max(kk - PF, 0)];
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
                for (int lx = 0; lx < TS; ++lx) valid[lx] = 0;
                for (int y = r0; y < r1; ++y) {
                    const T py = T(y) + T(0.5);
                    const T ry = (py - cy) / fy;
                    const int base = (y - y0) * TS;
                    // one pixel (16-lane loop or one 8-lane chunk, as in the forward); marks `valid`
                    auto lane = [&](const int lx) __attribute__((always_inline)) {
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
                        valid[lx] |= v ? 1 : 0;
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
#pragma omp simd
                        for (int lx = 0; lx < TS; ++lx) lane(lx);
                        if constexpr (K == K_RAYMAX) {
#pragma omp simd
                            for (int lx = 0; lx < TS; ++lx) proxy_lane(lx);
                        }
                    } else {
                        pairs += HL;
                        const int lb = h0 * HL;
#pragma omp simd
                        for (int l = 0; l < HL; ++l) lane(lb + l);
                        if constexpr (K == K_RAYMAX) {
#pragma omp simd
                            for (int l = 0; l < HL; ++l) proxy_lane(lb + l);
                        }
                    }
                }
                int any = 0;
#pragma omp simd reduction(| : any)
                for (int lx = 0; lx < TS; ++lx) any |= valid[lx];
                if (any == 0) continue;
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


}  // extern "C"
