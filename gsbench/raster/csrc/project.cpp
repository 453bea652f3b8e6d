// gsbench fused per-Gaussian projection (kernels ewa, rade, raymax and surfel): forward and a
// hand-written backward, one OpenMP loop over Gaussians each.
//
// Mirrors gsbench/raster/projection_torch.py `project_torch` operation for operation (that PyTorch code is the
// oracle; tests/test_raster_projection.py (ewa, rade) and tests/test_projection_fused_raymax_surfel.py
// (raymax, surfel) compare the two in float64 and gradcheck this one). Storage
// type T is float or double; every per-Gaussian quantity is computed in double (a few hundred flops per
// Gaussian, so this costs nothing measurable and removes the float32 overflow cases of 1/det for tiny
// covariances). Both passes run LANES Gaussians at a time in vector lanes (below, "Lanes"). The backward
// recomputes the forward intermediates instead of saving them, and skips a Gaussian whose payload gradient is
// all zero (its gradients are then 0: they are linear in it).
//
// Payload columns: see gsbench/raster/payload.py (common 0-8, ewa 9-12, rade 9-14, raymax 9-23, surfel 9-20).
// surfel reads only scales[:, :2] (the caller pads a third column, whose gradient is written as 0).

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <type_traits>
#include <omp.h>

extern "C" {

// Keep in sync with build.py (ProjArgs): 8-byte scalars and fixed double arrays only.
struct ProjArgs {
    int64_t n, dtype, kernel, sh_degree, sh_k, has_filter, width, height, tile, gx, gy, nthreads;
    double fx, fy, cx, cy, near_z, eps2d, aa, limx, limy;
    double R[9], t[3], C[3], L[16];
    // inputs (contiguous): means (N,3), quats (N,4), scales (N,3), opac (N,), sh (N,K,3), filter3d (N,) or null
    const void* means;
    const void* quats;
    const void* scales;
    const void* opac;
    const void* sh;
    const void* filter3d;
    // forward outputs
    void* params;          // (N, P) T
    void* means2d;         // (N, 2) T, 0 where not valid
    int64_t* radii;        // (N,)
    uint8_t* visible;      // (N,) bool
    void* depth;           // (N,) T centre z
    void* bounds;          // (N, 4) T
    int32_t* rect;         // (N, 4)
    int32_t* rect_radius;  // (N, 4)
    // backward
    const void* g_params;  // (N, P) T
    void* g_means;         // (N, 3) T (written, not accumulated)
    void* g_quats;         // (N, 4)
    void* g_scales;        // (N, 3)
    void* g_opac;          // (N,)
    void* g_sh;            // (N, K, 3) every row written (zero past the first (deg+1)², with g_sh_rest)
    double surfel_k;       // settings.surfel_filter (low-pass k; 0 = off); read only for surfel
    // the SH rows after the sh_k rows of sh, when the caller keeps them apart (as the training parameters
    // sh_dc / sh_rest): (N, sh_rest_k, 3) or null with sh_rest_k = 0; g_sh_rest likewise
    int64_t sh_rest_k;
    const void* sh_rest;
    void* g_sh_rest;
};

}  // extern "C"

namespace {

using D = double;
constexpr int K_EWA = 0, K_RADE = 1, K_RAYMAX = 2, K_SURFEL = 3;
constexpr D BIGV = 1.0e6;
constexpr D SURFEL_OFF = 1.0e6;  // px: the payload centre of a crossing surfel, off the image (no low-pass term)
constexpr D SH0 = 0.28209479177387814;
constexpr D SH1 = 0.4886025119029199;
constexpr D SH2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
                      0.5462742152960396};
constexpr D SH3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
                      -0.4570457994644658, 1.445305721320277, -0.5900435899266435};

// SH coefficient row k (3 values) of Gaussian i: row k of sh for k < sh_k, else row k − sh_k of sh_rest.
template <typename T>
inline const T* sh_row(const ProjArgs& A, int64_t i, int k) {
    return k < A.sh_k ? (const T*)A.sh + (i * A.sh_k + k) * 3 : (const T*)A.sh_rest + (i * A.sh_rest_k + k - A.sh_k) * 3;
}

template <typename T>
inline T* g_sh_row(const ProjArgs& A, int64_t i, int k) {
    return k < A.sh_k ? (T*)A.g_sh + (i * A.sh_k + k) * 3 : (T*)A.g_sh_rest + (i * A.sh_rest_k + k - A.sh_k) * 3;
}

template <int KER>
constexpr int nparams() { return KER == K_EWA ? 13 : KER == K_RADE ? 15 : KER == K_RAYMAX ? 24 : 21; }

// Lanes. The forward and the backward evaluate LANES Gaussians at a time in GCC vector lanes (values V8, masks
// M8: -1 true, 0 false); the same template code instantiated on (double, bool) is the one-Gaussian path, for
// the Gaussians left over. A lane computes both sides of every select and keeps one, so a lane's discarded side
// may hold inf or NaN; no kept value depends on it.
constexpr int LANES = 8;
typedef D V8 __attribute__((vector_size(LANES * sizeof(D))));
typedef int64_t M8 __attribute__((vector_size(LANES * sizeof(int64_t))));

template <typename V> struct LaneTraits { using M = bool; static constexpr int n = 1; };
template <> struct LaneTraits<V8> { using M = M8; static constexpr int n = LANES; };
template <typename V> using MaskOf = typename LaneTraits<V>::M;

template <typename V> inline V splat(D x) {
    if constexpr (std::is_same_v<V, D>) return x; else return x + V8{};
}
inline D lane(D x, int) { return x; }
inline D lane(V8 x, int l) { return x[l]; }
inline bool lane(bool m, int) { return m; }
inline bool lane(M8 m, int l) { return m[l] != 0; }
inline D sel(bool m, D a, D b) { return m ? a : b; }
inline V8 sel(M8 m, V8 a, V8 b) { return m ? a : b; }
inline bool mand(bool a, bool b) { return a && b; }
inline M8 mand(M8 a, M8 b) { return a & b; }
inline bool mnot(bool a) { return !a; }
inline M8 mnot(M8 a) { return ~a; }
// std::max / std::min lane by lane (std::max(a, b) is a < b ? b : a; std::min(a, b) is b < a ? b : a)
template <typename V> inline V vmax(V a, V b) { return sel(a < b, b, a); }
template <typename V> inline V vmin(V a, V b) { return sel(b < a, b, a); }
inline V8 vmax(V8 a, D b) { return vmax(a, splat<V8>(b)); }
template <typename V> inline V clampv(V x, D lo, D hi) { return vmin(vmax(x, splat<V>(lo)), splat<V>(hi)); }
#define GSB_LANEWISE(name, fn)                                            \
    inline D name(D x) { return fn(x); }                                  \
    inline V8 name(V8 x) {                                                \
        V8 r;                                                             \
        for (int l = 0; l < LANES; ++l) r[l] = fn(x[l]);                  \
        return r;                                                         \
    }
GSB_LANEWISE(vsqrt, std::sqrt)
GSB_LANEWISE(vlog, std::log)
GSB_LANEWISE(vfloor, std::floor)
GSB_LANEWISE(vceil, std::ceil)
GSB_LANEWISE(vabs, std::abs)
#undef GSB_LANEWISE

// Element k of the rows of a (N, stride) array of storage type T that the lanes hold (rows[l] in lane l), as V.
template <typename V, typename T>
inline V gather(const T* base, const int64_t* rows, int64_t stride, int64_t k) {
    if constexpr (std::is_same_v<V, D>) {
        return (D)base[rows[0] * stride + k];
    } else {
        V8 r;
        for (int l = 0; l < LANES; ++l) r[l] = (D)base[rows[l] * stride + k];
        return r;
    }
}

template <typename T, typename V>
inline void scatter(T* base, const int64_t* rows, int64_t stride, int64_t k, V x) {
    for (int l = 0; l < LaneTraits<V>::n; ++l) base[rows[l] * stride + k] = (T)lane(x, l);
}

// The raw SH colour Σ_k b_k c_k (k < nb, in order) of each lane: row k of sh for k < sh_k, else row k − sh_k of
// sh_rest. Each lane reads its own rows, which are contiguous; a gather across the lanes per coefficient made
// the forward 1.4 times as slow (experiments/papers_size/README.md, "The projection in vector lanes"). Explicit fused
// multiply-adds: the same rounding whichever loop a row falls in (sh kept apart or not, lanes or one Gaussian).
template <typename V, typename T>
inline void sh_colour(const ProjArgs& A, const int64_t* rows, int nb, const V* bs, V* raw) {
    const int k_sh = std::min<int>(nb, (int)A.sh_k);
    for (int l = 0; l < LaneTraits<V>::n; ++l) {
        D acc[3] = {0, 0, 0};
        const T* row = (const T*)A.sh + rows[l] * A.sh_k * 3;
        for (int k = 0; k < k_sh; ++k)
            for (int c = 0; c < 3; ++c) acc[c] = std::fma(lane(bs[k], l), (D)row[3 * k + c], acc[c]);
        if (nb > k_sh) {
            const T* rest = (const T*)A.sh_rest + rows[l] * A.sh_rest_k * 3;
            for (int k = k_sh; k < nb; ++k)
                for (int c = 0; c < 3; ++c) acc[c] = std::fma(lane(bs[k], l), (D)rest[3 * (k - k_sh) + c], acc[c]);
        }
        for (int c = 0; c < 3; ++c) {
            if constexpr (std::is_same_v<V, D>) raw[c] = acc[c]; else raw[c][l] = acc[c];
        }
    }
}

// Whether z <= near in the storage type T, as the PyTorch path compares (z exactly at near).
template <typename T>
inline bool le_storage(D z, D near) { return (T)z <= (T)near; }
template <typename T>
inline M8 le_storage(V8 z, D near) {
    M8 m;
    for (int l = 0; l < LANES; ++l) m[l] = (T)z[l] <= (T)near ? -1 : 0;
    return m;
}

// Real SH basis (3DGS convention, sh.py) and optionally its derivative w.r.t. (x, y, z).
template <typename V>
inline void sh_basis(int deg, V x, V y, V z, V* b, V (*db)[3]) {
    b[0] = splat<V>(SH0);
    if (db) db[0][0] = db[0][1] = db[0][2] = splat<V>(0);
    if (deg < 1) return;
    b[1] = -SH1 * y;
    b[2] = SH1 * z;
    b[3] = -SH1 * x;
    if (db) {
        db[1][0] = db[1][2] = splat<V>(0), db[1][1] = splat<V>(-SH1);
        db[2][0] = db[2][1] = splat<V>(0), db[2][2] = splat<V>(SH1);
        db[3][1] = db[3][2] = splat<V>(0), db[3][0] = splat<V>(-SH1);
    }
    if (deg < 2) return;
    const V xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
    b[4] = SH2[0] * xy;
    b[5] = SH2[1] * yz;
    b[6] = SH2[2] * (2.0 * zz - xx - yy);
    b[7] = SH2[3] * xz;
    b[8] = SH2[4] * (xx - yy);
    if (db) {
        const V zero = splat<V>(0);
        db[4][0] = SH2[0] * y, db[4][1] = SH2[0] * x, db[4][2] = zero;
        db[5][0] = zero, db[5][1] = SH2[1] * z, db[5][2] = SH2[1] * y;
        db[6][0] = -2.0 * SH2[2] * x, db[6][1] = -2.0 * SH2[2] * y, db[6][2] = 4.0 * SH2[2] * z;
        db[7][0] = SH2[3] * z, db[7][1] = zero, db[7][2] = SH2[3] * x;
        db[8][0] = 2.0 * SH2[4] * x, db[8][1] = -2.0 * SH2[4] * y, db[8][2] = zero;
    }
    if (deg < 3) return;
    b[9] = SH3[0] * y * (3.0 * xx - yy);
    b[10] = SH3[1] * xy * z;
    b[11] = SH3[2] * y * (4.0 * zz - xx - yy);
    b[12] = SH3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
    b[13] = SH3[4] * x * (4.0 * zz - xx - yy);
    b[14] = SH3[5] * z * (xx - yy);
    b[15] = SH3[6] * x * (xx - 3.0 * yy);
    if (db) {
        const V zero = splat<V>(0);
        db[9][0] = SH3[0] * 6.0 * xy, db[9][1] = SH3[0] * (3.0 * xx - 3.0 * yy), db[9][2] = zero;
        db[10][0] = SH3[1] * yz, db[10][1] = SH3[1] * xz, db[10][2] = SH3[1] * xy;
        db[11][0] = -2.0 * SH3[2] * xy, db[11][1] = SH3[2] * (4.0 * zz - xx - 3.0 * yy), db[11][2] = 8.0 * SH3[2] * yz;
        db[12][0] = -6.0 * SH3[3] * xz, db[12][1] = -6.0 * SH3[3] * yz,
        db[12][2] = SH3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy);
        db[13][0] = SH3[4] * (4.0 * zz - 3.0 * xx - yy), db[13][1] = -2.0 * SH3[4] * xy, db[13][2] = 8.0 * SH3[4] * xz;
        db[14][0] = 2.0 * SH3[5] * xz, db[14][1] = -2.0 * SH3[5] * yz, db[14][2] = SH3[5] * (xx - yy);
        db[15][0] = SH3[6] * (3.0 * xx - 3.0 * yy), db[15][1] = -6.0 * SH3[6] * xy, db[15][2] = zero;
    }
}

// Forward intermediates of one Gaussian (V = D, M = bool) or of LANES of them (V8, M8).
template <typename V>
struct Fw {
    using M = MaskOf<V>;
    V qr[4], qn, qden, q[4];
    V s[3], s2[3], s2f[3], se[3], o, o1, fo, o2;
    V m[3], mu[3], z, zs;
    M culled;
    V qc[4], Rc[9];
    V dv[3], dn, dden, dir[3], raw[3], rgb[3];
    V u, v, uc, vc;
    M inx, iny;
    V M_[9], r0[3], r1[3], a0, b, c0, cr[3], gdet;
    V a, c, det, det0, fac;
    M okk, ok;
    V conic[3];
    // ewa: the normal is column idx of Rc (idx the smallest scale: 1 if pick1, 2 if pick2, else 0) times sgn
    M pick1, pick2;
    V sgn, ncol[3];
    // rade
    V dc[3], dt[3], dm, h[3], mvec[3], nn2, sq, lc, dms, p0, p1, mut[3], w[3], bvec[3], l, bnorm, bden, nrm[3];
    // raymax (mut shared with rade): E = Rc S⁻¹ (rows ẽ_i), S6 = E Eᵀ (00,01,02,11,12,22), braw = E μ̃,
    // cs = μ̃·μ̃ (1 if culled), sq = √cs, muh = μ̃/sq, vx = muh × ẽ_0, vy = muh × ẽ_1, dM = (vx·vx, vx·vy, vy·vy)
    V E[9], S6[6], braw[3], cs, sqc, muh[3], vx[3], vy[3], dM[3];
    // surfel: X rows (se_u t_u, se_v t_v, μ) per camera axis, cos = −μ·t_w, sign, dd, dds, centre (cnx, cny);
    // crossing: the 3σ disc reaches the camera plane (dd >= 0), so it has no screen box (contract, surfel)
    V X[9], cosv, sgs, snrm[3], dd, dds, cnx, cny, dpl, au[3], av[3], mau, mav;
    M crossing;
};

template <typename T, int KER, typename V>
__attribute__((always_inline)) inline void forward_one(const ProjArgs& A, const int64_t* rows, Fw<V>& f) {
    const T* means = (const T*)A.means;
    const D fx = A.fx, fy = A.fy;
    for (int k = 0; k < 4; ++k) f.qr[k] = gather<V>((const T*)A.quats, rows, 4, k);
    f.qn = vsqrt(f.qr[0] * f.qr[0] + f.qr[1] * f.qr[1] + f.qr[2] * f.qr[2] + f.qr[3] * f.qr[3]);
    f.qden = vmax(f.qn, 1e-12);
    for (int k = 0; k < 4; ++k) f.q[k] = f.qr[k] / f.qden;
    constexpr int NC = KER == K_SURFEL ? 2 : 3;  // scale columns in use
    for (int k = 0; k < 3; ++k) f.s[k] = gather<V>((const T*)A.scales, rows, 3, k);
    f.o = gather<V>((const T*)A.opac, rows, 1, 0);
    if (A.has_filter) {
        const V f3 = gather<V>((const T*)A.filter3d, rows, 1, 0);
        V ratio = splat<V>(1.0);
        f.se[2] = f.s[2];
        for (int k = 0; k < NC; ++k) {
            f.s2[k] = f.s[k] * f.s[k];
            f.s2f[k] = f.s2[k] + f3;
            ratio *= f.s2[k] / f.s2f[k];
            f.se[k] = vsqrt(f.s2f[k]);
        }
        f.fo = vsqrt(ratio);
        f.o1 = f.o * f.fo;
    } else {
        for (int k = 0; k < 3; ++k) f.se[k] = f.s[k];
        f.fo = splat<V>(1.0);
        f.o1 = f.o;
    }
    for (int k = 0; k < 3; ++k) f.m[k] = gather<V>(means, rows, 3, k);
    for (int r = 0; r < 3; ++r)
        f.mu[r] = A.R[3 * r] * f.m[0] + A.R[3 * r + 1] * f.m[1] + A.R[3 * r + 2] * f.m[2] + A.t[r];
    f.z = f.mu[2];
    f.culled = le_storage<T>(f.z, A.near_z);
    f.zs = sel(f.culled, splat<V>(1.0), f.z);
    for (int r = 0; r < 4; ++r)
        f.qc[r] = A.L[4 * r] * f.q[0] + A.L[4 * r + 1] * f.q[1] + A.L[4 * r + 2] * f.q[2] + A.L[4 * r + 3] * f.q[3];
    {
        const V w = f.qc[0], x = f.qc[1], y = f.qc[2], z = f.qc[3];
        const V xx = x * x, yy = y * y, zz = z * z, xy = x * y, xz = x * z, yz = y * z, wx = w * x, wy = w * y,
                wz = w * z;
        V* R = f.Rc;
        R[0] = 1 - 2 * (yy + zz), R[1] = 2 * (xy - wz), R[2] = 2 * (xz + wy);
        R[3] = 2 * (xy + wz), R[4] = 1 - 2 * (xx + zz), R[5] = 2 * (yz - wx);
        R[6] = 2 * (xz - wy), R[7] = 2 * (yz + wx), R[8] = 1 - 2 * (xx + yy);
    }
    // SH colour
    const int deg = (int)A.sh_degree;
    if (deg == 0) {
        for (int ch = 0; ch < 3; ++ch) f.raw[ch] = SH0 * gather<V>((const T*)A.sh, rows, 3 * A.sh_k, ch);
    } else {
        for (int k = 0; k < 3; ++k) f.dv[k] = f.m[k] - A.C[k];
        f.dn = vsqrt(f.dv[0] * f.dv[0] + f.dv[1] * f.dv[1] + f.dv[2] * f.dv[2]);
        f.dden = vmax(f.dn, 1e-12);
        for (int k = 0; k < 3; ++k) f.dir[k] = f.dv[k] / f.dden;
        V bs[16];
        sh_basis<V>(deg, f.dir[0], f.dir[1], f.dir[2], bs, nullptr);
        sh_colour<V, T>(A, rows, (deg + 1) * (deg + 1), bs, f.raw);
    }
    for (int ch = 0; ch < 3; ++ch) f.rgb[ch] = vmax(f.raw[ch] + 0.5, splat<V>(0.0));

    f.u = f.mu[0] / f.zs;
    f.v = f.mu[1] / f.zs;
    if constexpr (KER == K_SURFEL) {
        for (int r = 0; r < 3; ++r) {
            f.X[3 * r] = f.se[0] * f.Rc[3 * r];
            f.X[3 * r + 1] = f.se[1] * f.Rc[3 * r + 1];
            f.X[3 * r + 2] = f.mu[r];
        }
        f.cosv = -(f.mu[0] * f.Rc[2] + f.mu[1] * f.Rc[5] + f.mu[2] * f.Rc[8]);
        f.sgs = sel(f.cosv >= 0, splat<V>(1.0), splat<V>(-1.0));
        for (int r = 0; r < 3; ++r) f.snrm[r] = f.Rc[3 * r + 2] * f.sgs;
        const V* X2 = f.X + 6;
        f.dd = 9.0 * (X2[0] * X2[0] + X2[1] * X2[1]) - X2[2] * X2[2];
        f.ok = mand(f.cosv != 0, mnot(f.culled));
        f.crossing = mand(f.ok, f.dd >= 0);
        f.dds = sel(mand(f.ok, mnot(f.crossing)), f.dd, splat<V>(-1.0));
        const V f0 = 9.0 / f.dds, f2 = -1.0 / f.dds;
        f.cnx = f0 * (f.X[0] * X2[0]) + f0 * (f.X[1] * X2[1]) + f2 * (f.X[2] * X2[2]);
        f.cny = f0 * (f.X[3] * X2[0]) + f0 * (f.X[4] * X2[1]) + f2 * (f.X[5] * X2[2]);
        f.dpl = f.snrm[0] * f.mu[0] + f.snrm[1] * f.mu[1] + f.snrm[2] * f.mu[2];
        f.mau = f.mav = splat<V>(0);
        for (int r = 0; r < 3; ++r) {
            f.au[r] = f.Rc[3 * r] / f.se[0];
            f.av[r] = f.Rc[3 * r + 1] / f.se[1];
            f.mau += f.mu[r] * f.au[r];
            f.mav += f.mu[r] * f.av[r];
        }
        f.o2 = f.o1;
        return;
    }
    f.inx = mand(f.u >= -A.limx, f.u <= A.limx);
    f.iny = mand(f.v >= -A.limy, f.v <= A.limy);
    f.uc = vmin(vmax(f.u, splat<V>(-A.limx)), splat<V>(A.limx));
    f.vc = vmin(vmax(f.v, splat<V>(-A.limy)), splat<V>(A.limy));
    for (int r = 0; r < 3; ++r)
        for (int j = 0; j < 3; ++j) f.M_[3 * r + j] = f.Rc[3 * r + j] * f.se[j];
    const V ax = fx / f.zs, ay = fy / f.zs;
    for (int j = 0; j < 3; ++j) {
        f.r0[j] = ax * (f.M_[j] - f.uc * f.M_[6 + j]);
        f.r1[j] = ay * (f.M_[3 + j] - f.vc * f.M_[6 + j]);
    }
    f.a0 = f.r0[0] * f.r0[0] + f.r0[1] * f.r0[1] + f.r0[2] * f.r0[2];
    f.b = f.r0[0] * f.r1[0] + f.r0[1] * f.r1[1] + f.r0[2] * f.r1[2];
    f.c0 = f.r1[0] * f.r1[0] + f.r1[1] * f.r1[1] + f.r1[2] * f.r1[2];
    f.cr[0] = f.r0[1] * f.r1[2] - f.r0[2] * f.r1[1];
    f.cr[1] = f.r0[2] * f.r1[0] - f.r0[0] * f.r1[2];
    f.cr[2] = f.r0[0] * f.r1[1] - f.r0[1] * f.r1[0];
    f.gdet = f.cr[0] * f.cr[0] + f.cr[1] * f.cr[1] + f.cr[2] * f.cr[2];
    const D eps = A.eps2d, kk = A.aa, e1 = eps + kk;
    f.a = f.a0 + e1;
    f.c = f.c0 + e1;
    f.det = f.gdet + e1 * (f.a0 + f.c0) + e1 * e1;
    f.o2 = f.o1;
    f.fac = splat<V>(1.0);
    f.okk = f.culled != f.culled;  // false in every lane
    if (kk > 0) {
        f.det0 = f.gdet + eps * (f.a0 + f.c0) + eps * eps;
        f.okk = mand(mand(f.det > 0, f.det0 > 0), mnot(f.culled));
        f.fac = sel(f.okk, vsqrt(f.det0 / f.det), splat<V>(0.0));
        f.o2 = f.o1 * f.fac;
    }
    f.ok = mand(f.det > 0, mnot(f.culled));
    // where not ok the PyTorch path's values (never read: such Gaussians are not binned)
    f.conic[0] = sel(f.ok, f.c / f.det, f.c);
    f.conic[1] = sel(f.ok, -f.b / f.det, -f.b);
    f.conic[2] = sel(f.ok, f.a / f.det, f.a);

    if constexpr (KER == K_EWA) {
        // argmin of the scales, first index on ties
        f.pick1 = f.se[1] < f.se[0];
        f.pick2 = f.se[2] < sel(f.pick1, f.se[1], f.se[0]);
        V col[3];
        for (int r = 0; r < 3; ++r) col[r] = sel(f.pick2, f.Rc[3 * r + 2], sel(f.pick1, f.Rc[3 * r + 1], f.Rc[3 * r]));
        const V nd = col[0] * f.mu[0] + col[1] * f.mu[1] + col[2] * f.mu[2];
        f.sgn = sel(nd > 0, splat<V>(-1.0), splat<V>(1.0));
        for (int r = 0; r < 3; ++r) f.ncol[r] = f.sgn * col[r];
    } else if constexpr (KER == K_RAYMAX) {
        for (int j = 0; j < 3; ++j)
            f.mut[j] = (f.mu[0] * f.Rc[j] + f.mu[1] * f.Rc[3 + j] + f.mu[2] * f.Rc[6 + j]) / f.se[j];
        for (int r = 0; r < 3; ++r)
            for (int j = 0; j < 3; ++j) f.E[3 * r + j] = f.Rc[3 * r + j] / f.se[j];
        const V c_ = f.mut[0] * f.mut[0] + f.mut[1] * f.mut[1] + f.mut[2] * f.mut[2];
        f.cs = sel(f.culled, splat<V>(1.0), c_);
        const V* E = f.E;
        int t = 0;
        for (int a = 0; a < 3; ++a)
            for (int b = a; b < 3; ++b, ++t) f.S6[t] = E[3 * a] * E[3 * b] + E[3 * a + 1] * E[3 * b + 1] + E[3 * a + 2] * E[3 * b + 2];
        for (int a = 0; a < 3; ++a) f.braw[a] = E[3 * a] * f.mut[0] + E[3 * a + 1] * f.mut[1] + E[3 * a + 2] * f.mut[2];
        f.sqc = vsqrt(f.cs);
        for (int k = 0; k < 3; ++k) f.muh[k] = f.mut[k] / f.sqc;
        const V* e0 = E;
        const V* e1 = E + 3;
        f.vx[0] = f.muh[1] * e0[2] - f.muh[2] * e0[1];
        f.vx[1] = f.muh[2] * e0[0] - f.muh[0] * e0[2];
        f.vx[2] = f.muh[0] * e0[1] - f.muh[1] * e0[0];
        f.vy[0] = f.muh[1] * e1[2] - f.muh[2] * e1[1];
        f.vy[1] = f.muh[2] * e1[0] - f.muh[0] * e1[2];
        f.vy[2] = f.muh[0] * e1[1] - f.muh[1] * e1[0];
        f.dM[0] = f.vx[0] * f.vx[0] + f.vx[1] * f.vx[1] + f.vx[2] * f.vx[2];
        f.dM[1] = f.vx[0] * f.vy[0] + f.vx[1] * f.vy[1] + f.vx[2] * f.vy[2];
        f.dM[2] = f.vy[0] * f.vy[0] + f.vy[1] * f.vy[1] + f.vy[2] * f.vy[2];
    } else {
        f.dc[0] = f.uc, f.dc[1] = f.vc, f.dc[2] = splat<V>(1.0);
        f.dm = splat<V>(0);
        for (int j = 0; j < 3; ++j) {
            f.dt[j] = (f.dc[0] * f.Rc[j] + f.dc[1] * f.Rc[3 + j] + f.dc[2] * f.Rc[6 + j]) / f.se[j];
            f.dm += f.dt[j] * f.dt[j];
            f.h[j] = f.dt[j] / f.se[j];
        }
        for (int r = 0; r < 3; ++r) f.mvec[r] = f.Rc[3 * r] * f.h[0] + f.Rc[3 * r + 1] * f.h[1] + f.Rc[3 * r + 2] * f.h[2];
        f.nn2 = f.uc * f.uc + f.vc * f.vc + 1.0;
        f.sq = vsqrt(f.nn2);
        f.lc = f.zs * f.sq;
        f.dms = sel(f.culled, splat<V>(1.0), f.dm);
        f.p0 = -f.lc * (f.mvec[0] / f.dms - f.uc / f.nn2);
        f.p1 = -f.lc * (f.mvec[1] / f.dms - f.vc / f.nn2);
        for (int j = 0; j < 3; ++j) {
            f.mut[j] = (f.mu[0] * f.Rc[j] + f.mu[1] * f.Rc[3 + j] + f.mu[2] * f.Rc[6 + j]) / f.se[j];
            f.w[j] = f.mut[j] / f.se[j];
        }
        for (int r = 0; r < 3; ++r) f.bvec[r] = f.Rc[3 * r] * f.w[0] + f.Rc[3 * r + 1] * f.w[1] + f.Rc[3 * r + 2] * f.w[2];
        f.l = vsqrt(f.mu[0] * f.mu[0] + f.mu[1] * f.mu[1] + f.mu[2] * f.mu[2]);
        f.bnorm = vsqrt(f.bvec[0] * f.bvec[0] + f.bvec[1] * f.bvec[1] + f.bvec[2] * f.bvec[2]);
        f.bden = vmax(f.bnorm, 1e-12);
        for (int r = 0; r < 3; ++r) f.nrm[r] = -f.bvec[r] / f.bden;
    }
}

// _raymax_bounds (projection_torch.py): pixel box of the rays within Mahalanobis² k = 2τ of μ (τ > 0 checked by the caller).
template <typename V>
inline void raymax_bounds(const ProjArgs& A, const Fw<V>& f, V tau, V* bnd) {
    const V k = vmax(2.0 * tau, splat<V>(0.0));
    V S[9];
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
            S[3 * r + c] = f.M_[3 * r] * f.M_[3 * c] + f.M_[3 * r + 1] * f.M_[3 * c + 1] + f.M_[3 * r + 2] * f.M_[3 * c + 2];
    const V mz = f.mu[2];
    for (int axis = 0; axis < 2; ++axis) {
        const D fl = axis == 0 ? A.fx : A.fy, c0 = axis == 0 ? A.cx : A.cy;
        const V ma = f.mu[axis];
        const V Saa = S[4 * axis], Sa2 = S[3 * axis + 2], S22 = S[8];
        const V a2 = mz * mz - k * S22;
        const V bq = ma * mz - k * Sa2;
        const V disc = k * (mz * mz * Saa - 2 * ma * mz * Sa2 + ma * ma * S22) - k * k * (Saa * S22 - Sa2 * Sa2);
        const V sq = vsqrt(vmax(disc, splat<V>(0.0)));
        const auto ok = a2 > 1e-12 * mz * mz;
        const V a2s = sel(ok, a2, splat<V>(1.0));
        const V lo_p = fl * ((bq - sq) / a2s) + c0, hi_p = fl * ((bq + sq) / a2s) + c0;
        const V pad = 1e-3 * vabs(hi_p - lo_p) + 0.01;
        bnd[2 * axis] = sel(ok, lo_p - pad, splat<V>(-BIGV));
        bnd[2 * axis + 1] = sel(ok, hi_p + pad, splat<V>(BIGV));
    }
}

// _surfel_bounds (projection_torch.py): the exact box of u²+v² <= 2τ ∪ the low-pass disc k|Δ|² <= 2τ.
template <typename V>
inline void surfel_bounds(const ProjArgs& A, const Fw<V>& f, V tau, V mx, V my, V* bnd) {
    const V k = vmax(2.0 * tau, splat<V>(0.0));
    const V* X2 = f.X + 6;
    const V dd = k * (X2[0] * X2[0] + X2[1] * X2[1]) - X2[2] * X2[2];
    const auto ok = dd < -1e-12 * (X2[2] * X2[2]);
    const V dds = sel(ok, dd, splat<V>(-1.0));
    const V f0 = k / dds, f2 = -1.0 / dds;
    for (int axis = 0; axis < 2; ++axis) {
        const V* Xa = f.X + 3 * axis;
        const D fl = axis == 0 ? A.fx : A.fy, c0 = axis == 0 ? A.cx : A.cy;
        const V cn = f0 * (Xa[0] * X2[0]) + f0 * (Xa[1] * X2[1]) + f2 * (Xa[2] * X2[2]);
        const V h = cn * cn - (f0 * (Xa[0] * Xa[0]) + f0 * (Xa[1] * Xa[1]) + f2 * (Xa[2] * Xa[2]));
        const V ext = vsqrt(vmax(h, splat<V>(0.0)));
        const V lo = fl * (cn - ext) + c0, hi = fl * (cn + ext) + c0;
        const V pad = 1e-3 * vabs(hi - lo) + 0.01;
        bnd[2 * axis] = sel(ok, lo - pad, splat<V>(-BIGV));
        bnd[2 * axis + 1] = sel(ok, hi + pad, splat<V>(BIGV));
    }
    const D fk = A.surfel_k;
    if (fk <= 0) return;
    const V r = vsqrt(vmax(2.0 * tau / fk, splat<V>(0.0))) * 1.001 + 0.01;
    bnd[0] = vmin(bnd[0], mx - r);
    bnd[1] = vmax(bnd[1], mx + r);
    bnd[2] = vmin(bnd[2], my - r);
    bnd[3] = vmax(bnd[3], my + r);
}

// The forward of Gaussian i (V = D) or of Gaussians i .. i + LANES - 1 (V8): payload, radius, boxes, rectangles.
template <typename T, int KER, typename V>
__attribute__((always_inline)) inline void forward_store(const ProjArgs& A, int64_t i) {
    using M = MaskOf<V>;
    constexpr int P = nparams<KER>();
    const D ts = (D)A.tile, gx = (D)A.gx, gy = (D)A.gy;
    int64_t rows[LaneTraits<V>::n];
    for (int l = 0; l < LaneTraits<V>::n; ++l) rows[l] = i + l;
    Fw<V> f;
    forward_one<T, KER, V>(A, rows, f);
    T* p = (T*)A.params;
    const V zero = splat<V>(0.0);
    V mx, my;
    if constexpr (KER == K_SURFEL) {
        // a crossing disc: the projected centre, and in the payload a centre SURFEL_OFF px away, so the
        // low-pass term (k|centre − p|²) never applies to it (contract)
        mx = A.fx * sel(f.crossing, f.u, f.cnx) + A.cx;
        my = A.fy * sel(f.crossing, f.v, f.cny) + A.cy;
        for (int k = 2; k < 5; ++k) scatter(p, rows, P, k, zero);
        scatter(p, rows, P, 0, sel(f.crossing, mx + SURFEL_OFF, mx));
    } else {
        mx = A.fx * f.u + A.cx;
        my = A.fy * f.v + A.cy;
        for (int k = 0; k < 3; ++k) scatter(p, rows, P, 2 + k, f.conic[k]);
        scatter(p, rows, P, 0, mx);
    }
    scatter(p, rows, P, 1, my);
    scatter(p, rows, P, 5, sel(f.ok, f.o2, zero));
    for (int ch = 0; ch < 3; ++ch) scatter(p, rows, P, 6 + ch, f.rgb[ch]);
    if constexpr (KER == K_EWA) {
        scatter(p, rows, P, 9, f.z);
        for (int r = 0; r < 3; ++r) scatter(p, rows, P, 10 + r, f.ncol[r]);
    } else if constexpr (KER == K_RADE) {
        scatter(p, rows, P, 9, f.l);
        scatter(p, rows, P, 10, f.p0 / A.fx);
        scatter(p, rows, P, 11, f.p1 / A.fy);
        for (int r = 0; r < 3; ++r) scatter(p, rows, P, 12 + r, f.nrm[r]);
    } else if constexpr (KER == K_RAYMAX) {
        for (int t = 0; t < 6; ++t) scatter(p, rows, P, 9 + t, f.S6[t] / f.cs);
        for (int a = 0; a < 3; ++a) scatter(p, rows, P, 15 + a, f.braw[a] / f.cs);
        for (int a = 0; a < 3; ++a) scatter(p, rows, P, 18 + a, f.dM[a] / f.cs);
        scatter(p, rows, P, 21, f.cs);
        scatter(p, rows, P, 22, f.u);
        scatter(p, rows, P, 23, f.v);
    } else {
        for (int r = 0; r < 3; ++r) scatter(p, rows, P, 9 + r, f.snrm[r]);
        scatter(p, rows, P, 12, f.dpl);
        for (int r = 0; r < 3; ++r) scatter(p, rows, P, 13 + r, f.au[r]);
        scatter(p, rows, P, 16, f.mau);
        for (int r = 0; r < 3; ++r) scatter(p, rows, P, 17 + r, f.av[r]);
        scatter(p, rows, P, 20, f.mav);
    }
    // radius, alpha-support box, tile rectangles (no gradient)
    const V tau = vlog(vmax(255.0 * f.o1, splat<V>(1e-30)));
    V radius, bnd[4];
    if constexpr (KER == K_SURFEL) {
        const V f0 = 9.0 / f.dds, f2 = -1.0 / f.dds;
        const V hnx = f.cnx * f.cnx - (f0 * (f.X[0] * f.X[0]) + f0 * (f.X[1] * f.X[1]) + f2 * (f.X[2] * f.X[2]));
        const V hny = f.cny * f.cny - (f0 * (f.X[3] * f.X[3]) + f0 * (f.X[4] * f.X[4]) + f2 * (f.X[5] * f.X[5]));
        const V ext_x = vsqrt(vmax(A.fx * A.fx * hnx, splat<V>(1e-4)));
        const V ext_y = vsqrt(vmax(A.fy * A.fy * hny, splat<V>(1e-4)));
        const D fl = A.surfel_k > 0 ? 3.0 / std::sqrt(A.surfel_k) : 0.0;
        radius = sel(f.ok, vceil(vmax(vmax(ext_x, ext_y), splat<V>(fl))), zero);
        // a crossing disc: a radius that reaches every image corner, so the tile rectangle is the whole image
        const V dx = vmax(vabs(mx), vabs(mx - (D)A.width));
        const V dy = vmax(vabs(my), vabs(my - (D)A.height));
        radius = sel(f.crossing, vceil(vsqrt(dx * dx + dy * dy)) + 1.0, radius);
        surfel_bounds(A, f, tau, mx, my, bnd);
    } else {
        const V mid = 0.5 * (f.a + f.c);
        const V lam = mid + vsqrt(vmax(mid * mid - f.det, splat<V>(0.1)));
        radius = sel(f.ok, vceil(3.0 * vsqrt(vmax(lam, zero))), zero);
        if constexpr (KER == K_RAYMAX) {
            raymax_bounds(A, f, tau, bnd);
        } else {
            const V t2 = 2.0 * tau;
            const V hx = vsqrt(t2 * f.a) * 1.001 + 0.01, hy = vsqrt(t2 * f.c) * 1.001 + 0.01;
            bnd[0] = mx - hx, bnd[1] = mx + hx, bnd[2] = my - hy, bnd[3] = my + hy;
        }
        const M has_support = tau > 0;  // else an empty box
        for (int k = 0; k < 4; ++k) bnd[k] = sel(has_support, bnd[k], splat<V>(k % 2 == 0 ? BIGV : -BIGV));
    }
    for (int k = 0; k < 4; ++k) bnd[k] = clampv(bnd[k], -BIGV, BIGV);
    const V rr[4] = {
        clampv(vfloor((mx - radius) / ts), 0, gx), clampv(vfloor((mx + radius + ts - 1) / ts), 0, gx),
        clampv(vfloor((my - radius) / ts), 0, gy), clampv(vfloor((my + radius + ts - 1) / ts), 0, gy)};
    const V rb[4] = {
        clampv(vfloor((bnd[0] - 0.5) / ts), 0, gx), clampv(vfloor((bnd[1] - 0.5) / ts) + 1, 0, gx),
        clampv(vfloor((bnd[2] - 0.5) / ts), 0, gy), clampv(vfloor((bnd[3] - 0.5) / ts) + 1, 0, gy)};
    const M vis = mand(mand(f.ok, radius > 0), (rr[1] - rr[0]) * (rr[3] - rr[2]) > 0);
    V rc[4] = {vmax(rr[0], rb[0]), vmin(rr[1], rb[1]), vmax(rr[2], rb[2]), vmin(rr[3], rb[3])};
    rc[1] = vmax(rc[1], rc[0]);
    rc[3] = vmax(rc[3], rc[2]);
    for (int l = 0; l < LaneTraits<V>::n; ++l) {
        const int64_t g = i + l;
        const bool vl = lane(vis, l), okl = lane(f.ok, l);
        for (int k = 0; k < 4; ++k) {
            A.rect[4 * g + k] = vl ? (int32_t)lane(rc[k], l) : 0;
            A.rect_radius[4 * g + k] = vl ? (int32_t)lane(rr[k], l) : 0;
        }
        A.radii[g] = vl ? (int64_t)lane(radius, l) : 0;
        A.visible[g] = vl ? 1 : 0;
        T* m2 = (T*)A.means2d + 2 * g;
        m2[0] = okl ? (T)lane(mx, l) : T(0);
        m2[1] = okl ? (T)lane(my, l) : T(0);
        ((T*)A.depth)[g] = (T)lane(f.z, l);
        T* bo = (T*)A.bounds + 4 * g;
        for (int k = 0; k < 4; ++k) bo[k] = (T)lane(bnd[k], l);
    }
}

template <typename T, int KER>
void project_forward(const ProjArgs& A) {
    const int64_t blocks = A.n / LANES;
#pragma omp parallel for num_threads((int)A.nthreads) schedule(static, 128)
    for (int64_t b = 0; b < blocks; ++b) forward_store<T, KER, V8>(A, b * LANES);
    for (int64_t i = blocks * LANES; i < A.n; ++i) forward_store<T, KER, D>(A, i);
}

// c = a × b: accumulate dL/da += b × g, dL/db += g × a.
template <typename V>
inline void cross_bwd(const V* a, const V* b, const V* g, V* ga, V* gb) {
    ga[0] += b[1] * g[2] - b[2] * g[1];
    ga[1] += b[2] * g[0] - b[0] * g[2];
    ga[2] += b[0] * g[1] - b[1] * g[0];
    gb[0] += g[1] * a[2] - g[2] * a[1];
    gb[1] += g[2] * a[0] - g[0] * a[2];
    gb[2] += g[0] * a[1] - g[1] * a[0];
}

// Whether the P payload gradients of a Gaussian are all 0: those of the Gaussians no pixel reached (outside the
// view, or behind pixels that stopped), 60-66% of them at a trained papers'-size state (experiments/papers_size/README.md).
template <typename T, int P>
inline bool zero_row(const T* gp) {
    bool zero = true;
    for (int k = 0; k < P; ++k) zero &= gp[k] == T(0);
    return zero;
}

// The gradients of a Gaussian with zero payload gradients: 0 for every input row, SH rows included.
template <typename T>
inline void write_zero_gradients(const ProjArgs& A, int64_t i) {
    std::fill_n((T*)A.g_means + 3 * i, 3, T(0));
    std::fill_n((T*)A.g_quats + 4 * i, 4, T(0));
    std::fill_n((T*)A.g_scales + 3 * i, 3, T(0));
    ((T*)A.g_opac)[i] = T(0);
    for (int k = 0; k < A.sh_k + A.sh_rest_k; ++k) std::fill_n(g_sh_row<T>(A, i, k), 3, T(0));
}

template <typename V>
inline void set_lane(V& x, int l, D value) {
    if constexpr (std::is_same_v<V, D>) x = value; else x[l] = value;
}

// The SH colour's backward, lane by lane (each lane's rows are contiguous, as in sh_colour): dL/dc_k = b_k dL/draw
// for every active row k (written; the rows past the active degree get 0), and dL/ddir = Σ_k (∂b_k/∂dir)(c_k ·
// dL/draw).
template <typename V, typename T>
inline void sh_colour_backward(const ProjArgs& A, const int64_t* rows, int nb, const V* bs, const V (*db)[3],
                               const V* graw, V* gdir) {
    for (int l = 0; l < LaneTraits<V>::n; ++l) {
        const D gr[3] = {lane(graw[0], l), lane(graw[1], l), lane(graw[2], l)};
        D gd[3] = {0, 0, 0};
        for (int k = 0; k < nb; ++k) {
            const T* row = sh_row<T>(A, rows[l], k);
            T* grow = g_sh_row<T>(A, rows[l], k);
            D s = 0;
            for (int ch = 0; ch < 3; ++ch) {
                grow[ch] = (T)(lane(bs[k], l) * gr[ch]);
                s += (D)row[ch] * gr[ch];
            }
            for (int d = 0; d < 3; ++d) gd[d] += lane(db[k][d], l) * s;
        }
        for (int d = 0; d < 3; ++d) set_lane(gdir[d], l, gd[d]);
        for (int k = nb; k < A.sh_k + A.sh_rest_k; ++k) std::fill_n(g_sh_row<T>(A, rows[l], k), 3, T(0));
    }
}

// The backward of the Gaussians the lanes hold (rows[l] in lane l), each with a non-zero payload gradient: the
// forward recomputed, then every input's gradient written. Branches of the one-Gaussian code are selects, as in
// the forward; an `if (c) x += y` is x += (c ? y : 0), the same sum.
template <typename T, int KER, typename V>
__attribute__((always_inline)) inline void backward_rows(const ProjArgs& A, const int64_t* rows) {
    using M = MaskOf<V>;
    constexpr int P = nparams<KER>();
    constexpr int NC = KER == K_SURFEL ? 2 : 3;
    constexpr int NL = LaneTraits<V>::n;
    const D fx = A.fx, fy = A.fy;
    const V zero = splat<V>(0.0);
    Fw<V> f;
    forward_one<T, KER, V>(A, rows, f);
    V g[P];
    for (int k = 0; k < P; ++k) g[k] = gather<V>((const T*)A.g_params, rows, P, k);
    V gmu[3], gRc[9], gse[3], gm[3];
    for (V* a : {gmu, gse, gm}) a[0] = a[1] = a[2] = zero;
    for (V& x : gRc) x = zero;
    V guc = zero, gvc = zero, gu = zero, gv = zero, gzs = zero, go1 = zero;

    // SH colour
    const int deg = (int)A.sh_degree;
    const int nb = (deg + 1) * (deg + 1);
    V graw[3];
    for (int ch = 0; ch < 3; ++ch) graw[ch] = sel(f.raw[ch] + 0.5 >= 0.0, g[6 + ch], zero);
    if (deg == 0) {
        for (int l = 0; l < NL; ++l) {
            T* gsh = g_sh_row<T>(A, rows[l], 0);
            for (int ch = 0; ch < 3; ++ch) gsh[ch] = (T)(SH0 * lane(graw[ch], l));
            for (int k = 1; k < A.sh_k + A.sh_rest_k; ++k) std::fill_n(g_sh_row<T>(A, rows[l], k), 3, T(0));
        }
    } else {
        V bs[16], db[16][3];
        sh_basis<V>(deg, f.dir[0], f.dir[1], f.dir[2], bs, db);
        V gdir[3];
        sh_colour_backward<V, T>(A, rows, nb, bs, db, graw, gdir);
        const M dir_ok = f.dn >= 1e-12;
        const V pr = f.dir[0] * gdir[0] + f.dir[1] * gdir[1] + f.dir[2] * gdir[2];
        for (int k = 0; k < 3; ++k) gm[k] += sel(dir_ok, (gdir[k] - f.dir[k] * pr) / f.dden, gdir[k] / f.dden);
    }

    if constexpr (KER == K_SURFEL) {
        go1 += sel(f.ok, g[5], zero);
        // extras: n = t_w·sign (sign constant), d = n·μ, a_u = t_u/se_u, μ·a_u, a_v = t_v/se_v, μ·a_v
        for (int r = 0; r < 3; ++r) {
            gRc[3 * r + 2] += f.sgs * (g[9 + r] + g[12] * f.mu[r]);
            gmu[r] += g[12] * f.snrm[r] + g[16] * f.au[r] + g[20] * f.av[r];
            const V gau = g[13 + r] + g[16] * f.mu[r], gav = g[17 + r] + g[20] * f.mu[r];
            gRc[3 * r] += gau / f.se[0];
            gRc[3 * r + 1] += gav / f.se[1];
            gse[0] -= gau * f.au[r] / f.se[0];
            gse[1] -= gav * f.av[r] / f.se[1];
        }
        // centre: cn_a = (9 Xa0 X20 + 9 Xa1 X21 − Xa2 X22)/dds, dds = dd (ok) = 9(X20² + X21²) − X22²
        V gX[9];
        for (V& x : gX) x = zero;
        const V keep = sel(f.crossing, zero, splat<V>(1.0));  // a crossing disc's payload centre is a constant
        const V gcn[2] = {keep * fx * g[0], keep * fy * g[1]};
        const V cn[2] = {f.cnx, f.cny};
        V gdds = zero;
        const V* X = f.X;
        for (int a = 0; a < 2; ++a) {
            const V gN = gcn[a] / f.dds;
            gdds -= gcn[a] * cn[a] / f.dds;
            gX[3 * a] += 9.0 * X[6] * gN;
            gX[6] += 9.0 * X[3 * a] * gN;
            gX[3 * a + 1] += 9.0 * X[7] * gN;
            gX[7] += 9.0 * X[3 * a + 1] * gN;
            gX[3 * a + 2] -= X[8] * gN;
            gX[8] -= X[3 * a + 2] * gN;
        }
        gX[6] += sel(f.ok, 18.0 * X[6] * gdds, zero);
        gX[7] += sel(f.ok, 18.0 * X[7] * gdds, zero);
        gX[8] -= sel(f.ok, 2.0 * X[8] * gdds, zero);
        // X rows: (se_u Rc_r0, se_v Rc_r1, μ_r)
        for (int r = 0; r < 3; ++r) {
            gRc[3 * r] += f.se[0] * gX[3 * r];
            gse[0] += f.Rc[3 * r] * gX[3 * r];
            gRc[3 * r + 1] += f.se[1] * gX[3 * r + 1];
            gse[1] += f.Rc[3 * r + 1] * gX[3 * r + 1];
            gmu[r] += gX[3 * r + 2];
        }
    } else {
        // means2d = (fx u + cx, fy v + cy)
        gu += fx * g[0];
        gv += fy * g[1];

        // kernel extras
        if constexpr (KER == K_EWA) {
            gmu[2] += g[9];
            // the normal is sgn × column idx of Rc
            const M in_col[3] = {mand(mnot(f.pick1), mnot(f.pick2)), mand(f.pick1, mnot(f.pick2)), f.pick2};
            for (int r = 0; r < 3; ++r)
                for (int j = 0; j < 3; ++j) gRc[3 * r + j] += sel(in_col[j], f.sgn * g[10 + r], zero);
        } else if constexpr (KER == K_RAYMAX) {
            const V inv = 1.0 / f.cs;
            const V* E = f.E;
            V gE[9], gmut[3] = {zero, zero, zero};
            for (V& x : gE) x = zero;
            V ginv = zero, gcs = g[21];
            // A' = E Eᵀ / cs
            int t = 0;
            for (int a = 0; a < 3; ++a)
                for (int b = a; b < 3; ++b, ++t) {
                    const V ga = g[9 + t];
                    ginv += ga * f.S6[t];
                    for (int j = 0; j < 3; ++j) {
                        gE[3 * a + j] += ga * inv * E[3 * b + j];
                        gE[3 * b + j] += ga * inv * E[3 * a + j];
                    }
                }
            // b' = E μ̃ / cs
            for (int a = 0; a < 3; ++a) {
                const V gb = g[15 + a];
                ginv += gb * f.braw[a];
                for (int j = 0; j < 3; ++j) {
                    gE[3 * a + j] += gb * inv * f.mut[j];
                    gmut[j] += gb * inv * E[3 * a + j];
                }
            }
            // M' = (vx·vx, vx·vy, vy·vy) / cs, vx = muh × ẽ_0, vy = muh × ẽ_1, muh = μ̃/√cs
            ginv += g[18] * f.dM[0] + g[19] * f.dM[1] + g[20] * f.dM[2];
            V gvx[3], gvy[3], gmuh[3] = {zero, zero, zero};
            for (int k = 0; k < 3; ++k) {
                gvx[k] = inv * (2.0 * g[18] * f.vx[k] + g[19] * f.vy[k]);
                gvy[k] = inv * (g[19] * f.vx[k] + 2.0 * g[20] * f.vy[k]);
            }
            cross_bwd(f.muh, E, gvx, gmuh, gE);
            cross_bwd(f.muh, E + 3, gvy, gmuh, gE + 3);
            V gsq = zero;
            for (int k = 0; k < 3; ++k) {
                gmut[k] += gmuh[k] / f.sqc;
                gsq -= gmuh[k] * f.muh[k] / f.sqc;
            }
            gcs += gsq / (2.0 * f.sqc) - ginv * inv * inv;
            for (int k = 0; k < 3; ++k) gmut[k] += sel(f.culled, zero, 2.0 * f.mut[k] * gcs);
            // μ̃_j = (Σ_r μ_r Rc_rj)/se_j, E_rj = Rc_rj/se_j
            for (int j = 0; j < 3; ++j) {
                const V gy = gmut[j] / f.se[j];
                gse[j] -= gmut[j] * f.mut[j] / f.se[j];
                for (int r = 0; r < 3; ++r) {
                    gmu[r] += f.Rc[3 * r + j] * gy;
                    gRc[3 * r + j] += f.mu[r] * gy + gE[3 * r + j] / f.se[j];
                    gse[j] -= gE[3 * r + j] * E[3 * r + j] / f.se[j];
                }
            }
            // (μx/μz, μy/μz) unclamped
            gu += g[22];
            gv += g[23];
        } else {
            // l = |mu|
            for (int k = 0; k < 3; ++k) gmu[k] += sel(f.l > 0, g[9] * f.mu[k] / f.l, zero);
            // nrm = -normalize(bvec)
            V gbv[3];
            {
                const V gbh[3] = {-g[12], -g[13], -g[14]};
                const M b_ok = f.bnorm >= 1e-12;
                const V bh[3] = {f.bvec[0] / f.bden, f.bvec[1] / f.bden, f.bvec[2] / f.bden};
                const V pr = bh[0] * gbh[0] + bh[1] * gbh[1] + bh[2] * gbh[2];
                for (int k = 0; k < 3; ++k) gbv[k] = sel(b_ok, (gbh[k] - bh[k] * pr) / f.bden, gbh[k] / f.bden);
            }
            // bvec_r = Σ_j Rc_rj w_j, w_j = mut_j / se_j, mut_j = (Σ_r mu_r Rc_rj) / se_j
            for (int j = 0; j < 3; ++j) {
                V gw = zero;
                for (int r = 0; r < 3; ++r) {
                    gRc[3 * r + j] += gbv[r] * f.w[j];
                    gw += f.Rc[3 * r + j] * gbv[r];
                }
                const V gmut = gw / f.se[j];
                gse[j] -= gw * f.w[j] / f.se[j];
                const V gy = gmut / f.se[j];
                gse[j] -= gmut * f.mut[j] / f.se[j];
                for (int r = 0; r < 3; ++r) {
                    gmu[r] += f.Rc[3 * r + j] * gy;
                    gRc[3 * r + j] += f.mu[r] * gy;
                }
            }
            // p0 = -lc (mvec0/dms - uc/nn2), p1 likewise; payload p/f
            const V gp0 = g[10] / fx, gp1 = g[11] / fy;
            const V e0 = f.mvec[0] / f.dms - f.uc / f.nn2, e1 = f.mvec[1] / f.dms - f.vc / f.nn2;
            const V glc = -e0 * gp0 - e1 * gp1;
            const V gmv[3] = {-f.lc / f.dms * gp0, -f.lc / f.dms * gp1, zero};
            const V gdms = f.lc * (f.mvec[0] * gp0 + f.mvec[1] * gp1) / (f.dms * f.dms);
            guc += f.lc / f.nn2 * gp0;
            gvc += f.lc / f.nn2 * gp1;
            V gnn2 = -f.lc * (f.uc * gp0 + f.vc * gp1) / (f.nn2 * f.nn2);
            // lc = zs sqrt(nn2)
            gzs += glc * f.sq;
            gnn2 += glc * f.zs / (2.0 * f.sq);
            guc += 2.0 * f.uc * gnn2;
            gvc += 2.0 * f.vc * gnn2;
            const V gdm = sel(f.culled, zero, gdms);
            // mvec_r = Σ_j Rc_rj h_j, h_j = dt_j/se_j; dm = Σ dt_j², dt_j = (Σ_r dc_r Rc_rj)/se_j
            V gdc[3] = {zero, zero, zero};
            for (int j = 0; j < 3; ++j) {
                V gh = zero;
                for (int r = 0; r < 3; ++r) {
                    gRc[3 * r + j] += gmv[r] * f.h[j];
                    gh += f.Rc[3 * r + j] * gmv[r];
                }
                V gdt = gh / f.se[j] + 2.0 * f.dt[j] * gdm;
                gse[j] -= gh * f.h[j] / f.se[j];
                const V ge = gdt / f.se[j];
                gse[j] -= gdt * f.dt[j] / f.se[j];
                for (int r = 0; r < 3; ++r) {
                    gRc[3 * r + j] += f.dc[r] * ge;
                    gdc[r] += f.Rc[3 * r + j] * ge;
                }
            }
            guc += gdc[0];
            gvc += gdc[1];
        }

        // conic and opacity
        const D eps = A.eps2d, kk = A.aa, e1 = eps + kk;
        V ga = zero, gb = zero, gc = zero, gdet = zero, gdet0 = zero;
        const V go2 = sel(f.ok, g[5], zero);
        if (kk > 0) {
            go1 += go2 * f.fac;
            const V gfac = go2 * f.o1;
            gdet0 += sel(f.okk, gfac * f.fac / (2.0 * f.det0), zero);
            gdet -= sel(f.okk, gfac * f.fac / (2.0 * f.det), zero);
        } else {
            go1 += go2;
        }
        {
            // ok: X = S⁻¹ = [[A, B], [B, C]]; dL/dS = -X G X with G = [[gA, gB/2], [gB/2, gC]]
            const V XA = f.conic[0], XB = f.conic[1], XC = f.conic[2];
            const V GA = g[2], GB = 0.5 * g[3], GC = g[4];
            // XG
            const V t00 = XA * GA + XB * GB, t01 = XA * GB + XB * GC;
            const V t10 = XB * GA + XC * GB, t11 = XB * GB + XC * GC;
            const V y00 = t00 * XA + t01 * XB, y01 = t00 * XB + t01 * XC, y11 = t10 * XB + t11 * XC;
            // not ok: the payload holds (c, -b, a)
            ga = sel(f.ok, ga - y00, ga + g[4]);
            gc = sel(f.ok, gc - y11, gc + g[2]);
            gb = sel(f.ok, gb - 2.0 * y01, gb - g[3]);
        }
        // a = a0 + e1, c = c0 + e1, det = gdet + e1 (a0 + c0) + e1², det0 = gdet + eps (a0 + c0) + eps²
        const V ga0 = ga + gdet * e1 + gdet0 * eps;
        const V gc0 = gc + gdet * e1 + gdet0 * eps;
        const V ggd = gdet + gdet0;
        V gr0[3], gr1[3];
        {
            const V gcr[3] = {2.0 * ggd * f.cr[0], 2.0 * ggd * f.cr[1], 2.0 * ggd * f.cr[2]};
            // cr = r0 × r1: g_r0 = r1 × gcr, g_r1 = gcr × r0
            gr0[0] = f.r1[1] * gcr[2] - f.r1[2] * gcr[1];
            gr0[1] = f.r1[2] * gcr[0] - f.r1[0] * gcr[2];
            gr0[2] = f.r1[0] * gcr[1] - f.r1[1] * gcr[0];
            gr1[0] = gcr[1] * f.r0[2] - gcr[2] * f.r0[1];
            gr1[1] = gcr[2] * f.r0[0] - gcr[0] * f.r0[2];
            gr1[2] = gcr[0] * f.r0[1] - gcr[1] * f.r0[0];
            for (int j = 0; j < 3; ++j) {
                gr0[j] += 2.0 * ga0 * f.r0[j] + gb * f.r1[j];
                gr1[j] += 2.0 * gc0 * f.r1[j] + gb * f.r0[j];
            }
        }
        // r0_j = (fx/zs)(M0j - uc M2j), r1_j = (fy/zs)(M1j - vc M2j)
        V gM[9];
        {
            const V ax = fx / f.zs, ay = fy / f.zs;
            V s0 = zero, s1 = zero, sr0 = zero, sr1 = zero;
            for (int j = 0; j < 3; ++j) {
                gM[j] = ax * gr0[j];
                gM[3 + j] = ay * gr1[j];
                gM[6 + j] = -ax * f.uc * gr0[j] - ay * f.vc * gr1[j];
                s0 += f.M_[6 + j] * gr0[j];
                s1 += f.M_[6 + j] * gr1[j];
                sr0 += f.r0[j] * gr0[j];
                sr1 += f.r1[j] * gr1[j];
            }
            guc -= ax * s0;
            gvc -= ay * s1;
            gzs -= (sr0 + sr1) / f.zs;
        }
        // clamp, u = mu0/zs, v = mu1/zs
        gu += sel(f.inx, guc, zero);
        gv += sel(f.iny, gvc, zero);
        gmu[0] += gu / f.zs;
        gmu[1] += gv / f.zs;
        gzs -= (f.u * gu + f.v * gv) / f.zs;
        gmu[2] += sel(f.culled, zero, gzs);
        // M = Rc diag(se)
        for (int r = 0; r < 3; ++r)
            for (int j = 0; j < 3; ++j) {
                gRc[3 * r + j] += gM[3 * r + j] * f.se[j];
                gse[j] += gM[3 * r + j] * f.Rc[3 * r + j];
            }
    }
    // Rc = rotmat(qc)
    V gqc[4];
    {
        const V w = f.qc[0], x = f.qc[1], y = f.qc[2], z = f.qc[3];
        const V* G = gRc;
        gqc[0] = 2.0 * (-z * G[1] + y * G[2] + z * G[3] - x * G[5] - y * G[6] + x * G[7]);
        gqc[1] = 2.0 * (-2.0 * x * G[4] - 2.0 * x * G[8] + y * G[1] + z * G[2] + y * G[3] - w * G[5] + z * G[6] + w * G[7]);
        gqc[2] = 2.0 * (-2.0 * y * G[0] - 2.0 * y * G[8] + x * G[1] + w * G[2] + x * G[3] + z * G[5] - w * G[6] + z * G[7]);
        gqc[3] = 2.0 * (-2.0 * z * G[0] - 2.0 * z * G[4] - w * G[1] + x * G[2] + w * G[3] + y * G[5] + x * G[6] + y * G[7]);
    }
    // qc = L q; q = qr / max(|qr|, 1e-12)
    V gq[4];
    for (int k = 0; k < 4; ++k) gq[k] = A.L[k] * gqc[0] + A.L[4 + k] * gqc[1] + A.L[8 + k] * gqc[2] + A.L[12 + k] * gqc[3];
    {
        const M q_ok = f.qn >= 1e-12;
        const V pr = f.q[0] * gq[0] + f.q[1] * gq[1] + f.q[2] * gq[2] + f.q[3] * gq[3];
        for (int k = 0; k < 4; ++k)
            scatter((T*)A.g_quats, rows, 4, k, sel(q_ok, (gq[k] - f.q[k] * pr) / f.qden, gq[k] / f.qden));
    }
    // mu = R m + t
    for (int k = 0; k < 3; ++k) gm[k] += A.R[k] * gmu[0] + A.R[3 + k] * gmu[1] + A.R[6 + k] * gmu[2];
    for (int k = 0; k < 3; ++k) scatter((T*)A.g_means, rows, 3, k, gm[k]);
    // 3D filter: se = sqrt(s² + f3), o1 = o sqrt(Π s²/(s² + f3)) over the NC scale columns in use
    if (A.has_filter) {
        const V gfo = go1 * f.o;
        for (int k = 0; k < NC; ++k) {
            const V gs2f = gse[k] / (2.0 * f.se[k]) - gfo * f.fo / (2.0 * f.s2f[k]);
            scatter((T*)A.g_scales, rows, 3, k, 2.0 * f.s[k] * gs2f + gfo * f.fo / f.s[k]);
        }
        if (NC == 2) scatter((T*)A.g_scales, rows, 3, 2, zero);
        scatter((T*)A.g_opac, rows, 1, 0, go1 * f.fo);
    } else {
        for (int k = 0; k < 3; ++k) scatter((T*)A.g_scales, rows, 3, k, k < NC ? gse[k] : zero);
        scatter((T*)A.g_opac, rows, 1, 0, go1);
    }
}

// One OpenMP loop over chunks of Gaussians: a Gaussian whose payload gradient is all zero gets zero gradients
// (they are linear in it); the others are listed and go through the backward LANES at a time, the chunk's last
// ones one at a time.
template <typename T, int KER>
void project_backward(const ProjArgs& A) {
    constexpr int P = nparams<KER>();
    constexpr int64_t CHUNK = 1024;
    const int64_t chunks = (A.n + CHUNK - 1) / CHUNK;
#pragma omp parallel for num_threads((int)A.nthreads) schedule(static, 1)
    for (int64_t c = 0; c < chunks; ++c) {
        int64_t rows[CHUNK];
        int64_t m = 0;
        for (int64_t i = c * CHUNK; i < std::min(A.n, (c + 1) * CHUNK); ++i) {
            if (zero_row<T, P>((const T*)A.g_params + i * P)) write_zero_gradients<T>(A, i);
            else rows[m++] = i;
        }
        int64_t j = 0;
        for (; j + LANES <= m; j += LANES) backward_rows<T, KER, V8>(A, rows + j);
        for (; j < m; ++j) backward_rows<T, KER, D>(A, rows + j);
    }
}

template <typename T>
int run(const ProjArgs& A, bool fwd) {
    switch (A.kernel) {
        case K_EWA: fwd ? project_forward<T, K_EWA>(A) : project_backward<T, K_EWA>(A); break;
        case K_RADE: fwd ? project_forward<T, K_RADE>(A) : project_backward<T, K_RADE>(A); break;
        case K_RAYMAX: fwd ? project_forward<T, K_RAYMAX>(A) : project_backward<T, K_RAYMAX>(A); break;
        case K_SURFEL: fwd ? project_forward<T, K_SURFEL>(A) : project_backward<T, K_SURFEL>(A); break;
        default: return -1;
    }
    return 0;
}

}  // namespace

extern "C" {

int gs_project_forward(ProjArgs* A) {
    if (A->sh_degree < 0 || A->sh_degree > 3) return -3;
    return A->dtype == 0 ? run<float>(*A, true) : run<double>(*A, true);
}

int gs_project_backward(ProjArgs* A) {
    if (A->sh_degree < 0 || A->sh_degree > 3) return -3;
    return A->dtype == 0 ? run<float>(*A, false) : run<double>(*A, false);
}

}  // extern "C"
