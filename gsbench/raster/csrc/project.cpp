// gsbench fused per-Gaussian projection for the EWA family (kernels ewa and rade): forward and a
// hand-written backward, one OpenMP loop over Gaussians each.
//
// Mirrors gsbench/raster/projection.py `_project_torch` operation for operation (that PyTorch code is the
// oracle; tests/test_raster_projection.py compares the two in float64 and gradchecks this one). Storage
// type T is float or double; every per-Gaussian quantity is computed in double (a few hundred flops per
// Gaussian, so this costs nothing measurable and removes the float32 overflow cases of 1/det for tiny
// covariances). The backward recomputes the forward intermediates instead of saving them.
//
// Payload columns: see projection.py (common 0-8, ewa 9-12, rade 9-14).

#include <algorithm>
#include <cmath>
#include <cstdint>
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
    void* g_sh;            // (N, K, 3) (zero-initialised by the caller; first (deg+1)² rows written)
};

}  // extern "C"

namespace {

using D = double;
constexpr int K_EWA = 0, K_RADE = 1;
constexpr D BIGV = 1.0e6;
constexpr D SH0 = 0.28209479177387814;
constexpr D SH1 = 0.4886025119029199;
constexpr D SH2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
                      0.5462742152960396};
constexpr D SH3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
                      -0.4570457994644658, 1.445305721320277, -0.5900435899266435};

inline int nparams(int kernel) { return kernel == K_EWA ? 13 : 15; }

// Real SH basis (3DGS convention, sh.py) and optionally its derivative w.r.t. (x, y, z).
inline void sh_basis(int deg, D x, D y, D z, D* b, D (*db)[3]) {
    b[0] = SH0;
    if (db) db[0][0] = db[0][1] = db[0][2] = 0;
    if (deg < 1) return;
    b[1] = -SH1 * y;
    b[2] = SH1 * z;
    b[3] = -SH1 * x;
    if (db) {
        db[1][0] = 0, db[1][1] = -SH1, db[1][2] = 0;
        db[2][0] = 0, db[2][1] = 0, db[2][2] = SH1;
        db[3][0] = -SH1, db[3][1] = 0, db[3][2] = 0;
    }
    if (deg < 2) return;
    const D xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
    b[4] = SH2[0] * xy;
    b[5] = SH2[1] * yz;
    b[6] = SH2[2] * (2.0 * zz - xx - yy);
    b[7] = SH2[3] * xz;
    b[8] = SH2[4] * (xx - yy);
    if (db) {
        db[4][0] = SH2[0] * y, db[4][1] = SH2[0] * x, db[4][2] = 0;
        db[5][0] = 0, db[5][1] = SH2[1] * z, db[5][2] = SH2[1] * y;
        db[6][0] = -2.0 * SH2[2] * x, db[6][1] = -2.0 * SH2[2] * y, db[6][2] = 4.0 * SH2[2] * z;
        db[7][0] = SH2[3] * z, db[7][1] = 0, db[7][2] = SH2[3] * x;
        db[8][0] = 2.0 * SH2[4] * x, db[8][1] = -2.0 * SH2[4] * y, db[8][2] = 0;
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
        db[9][0] = SH3[0] * 6.0 * xy, db[9][1] = SH3[0] * (3.0 * xx - 3.0 * yy), db[9][2] = 0;
        db[10][0] = SH3[1] * yz, db[10][1] = SH3[1] * xz, db[10][2] = SH3[1] * xy;
        db[11][0] = -2.0 * SH3[2] * xy, db[11][1] = SH3[2] * (4.0 * zz - xx - 3.0 * yy), db[11][2] = 8.0 * SH3[2] * yz;
        db[12][0] = -6.0 * SH3[3] * xz, db[12][1] = -6.0 * SH3[3] * yz,
        db[12][2] = SH3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy);
        db[13][0] = SH3[4] * (4.0 * zz - 3.0 * xx - yy), db[13][1] = -2.0 * SH3[4] * xy, db[13][2] = 8.0 * SH3[4] * xz;
        db[14][0] = 2.0 * SH3[5] * xz, db[14][1] = -2.0 * SH3[5] * yz, db[14][2] = SH3[5] * (xx - yy);
        db[15][0] = SH3[6] * (3.0 * xx - 3.0 * yy), db[15][1] = -6.0 * SH3[6] * xy, db[15][2] = 0;
    }
}

// Forward intermediates of one Gaussian.
struct Fw {
    D qr[4], qn, qden, q[4];
    D s[3], s2[3], s2f[3], se[3], o, o1, fo, o2;
    D m[3], mu[3], z, zs;
    bool culled;
    D qc[4], Rc[9];
    D dv[3], dn, dden, dir[3], raw[3], rgb[3];
    D u, v, uc, vc;
    bool inx, iny;
    D M[9], r0[3], r1[3], a0, b, c0, cr[3], gdet;
    D a, c, det, det0, fac;
    bool okk, ok;
    D conic[3];
    // ewa
    int idx;
    D sgn;
    // rade
    D dc[3], dt[3], dm, h[3], mvec[3], nn2, sq, lc, dms, p0, p1, mut[3], w[3], bvec[3], l, bnorm, bden, nrm[3];
};

template <typename T, int KER>
__attribute__((always_inline)) inline void forward_one(const ProjArgs& A, int64_t i, Fw& f) {
    const T* means = (const T*)A.means + 3 * i;
    const T* quats = (const T*)A.quats + 4 * i;
    const T* scales = (const T*)A.scales + 3 * i;
    const D fx = A.fx, fy = A.fy;
    for (int k = 0; k < 4; ++k) f.qr[k] = (D)quats[k];
    f.qn = std::sqrt(f.qr[0] * f.qr[0] + f.qr[1] * f.qr[1] + f.qr[2] * f.qr[2] + f.qr[3] * f.qr[3]);
    f.qden = std::max(f.qn, 1e-12);
    for (int k = 0; k < 4; ++k) f.q[k] = f.qr[k] / f.qden;
    for (int k = 0; k < 3; ++k) f.s[k] = (D)scales[k];
    f.o = (D)((const T*)A.opac)[i];
    if (A.has_filter) {
        const D f3 = (D)((const T*)A.filter3d)[i];
        D ratio = 1.0;
        for (int k = 0; k < 3; ++k) {
            f.s2[k] = f.s[k] * f.s[k];
            f.s2f[k] = f.s2[k] + f3;
            ratio *= f.s2[k] / f.s2f[k];
            f.se[k] = std::sqrt(f.s2f[k]);
        }
        f.fo = std::sqrt(ratio);
        f.o1 = f.o * f.fo;
    } else {
        for (int k = 0; k < 3; ++k) f.se[k] = f.s[k];
        f.fo = 1.0;
        f.o1 = f.o;
    }
    for (int k = 0; k < 3; ++k) f.m[k] = (D)means[k];
    for (int r = 0; r < 3; ++r)
        f.mu[r] = A.R[3 * r] * f.m[0] + A.R[3 * r + 1] * f.m[1] + A.R[3 * r + 2] * f.m[2] + A.t[r];
    f.z = f.mu[2];
    f.culled = (T)f.z <= (T)A.near_z;  // in the storage type, as the PyTorch path (z exactly at near)
    f.zs = f.culled ? 1.0 : f.z;
    for (int r = 0; r < 4; ++r)
        f.qc[r] = A.L[4 * r] * f.q[0] + A.L[4 * r + 1] * f.q[1] + A.L[4 * r + 2] * f.q[2] + A.L[4 * r + 3] * f.q[3];
    {
        const D w = f.qc[0], x = f.qc[1], y = f.qc[2], z = f.qc[3];
        const D xx = x * x, yy = y * y, zz = z * z, xy = x * y, xz = x * z, yz = y * z, wx = w * x, wy = w * y,
                wz = w * z;
        D* R = f.Rc;
        R[0] = 1 - 2 * (yy + zz), R[1] = 2 * (xy - wz), R[2] = 2 * (xz + wy);
        R[3] = 2 * (xy + wz), R[4] = 1 - 2 * (xx + zz), R[5] = 2 * (yz - wx);
        R[6] = 2 * (xz - wy), R[7] = 2 * (yz + wx), R[8] = 1 - 2 * (xx + yy);
    }
    // SH colour
    const int deg = (int)A.sh_degree;
    const T* sh = (const T*)A.sh + i * A.sh_k * 3;
    if (deg == 0) {
        for (int ch = 0; ch < 3; ++ch) f.raw[ch] = SH0 * (D)sh[ch];
    } else {
        for (int k = 0; k < 3; ++k) f.dv[k] = f.m[k] - A.C[k];
        f.dn = std::sqrt(f.dv[0] * f.dv[0] + f.dv[1] * f.dv[1] + f.dv[2] * f.dv[2]);
        f.dden = std::max(f.dn, 1e-12);
        for (int k = 0; k < 3; ++k) f.dir[k] = f.dv[k] / f.dden;
        D bs[16];
        sh_basis(deg, f.dir[0], f.dir[1], f.dir[2], bs, nullptr);
        const int nb = (deg + 1) * (deg + 1);
        for (int ch = 0; ch < 3; ++ch) {
            D acc = 0;
            for (int k = 0; k < nb; ++k) acc += bs[k] * (D)sh[3 * k + ch];
            f.raw[ch] = acc;
        }
    }
    for (int ch = 0; ch < 3; ++ch) f.rgb[ch] = std::max(f.raw[ch] + 0.5, 0.0);

    f.u = f.mu[0] / f.zs;
    f.v = f.mu[1] / f.zs;
    f.inx = f.u >= -A.limx && f.u <= A.limx;
    f.iny = f.v >= -A.limy && f.v <= A.limy;
    f.uc = std::min(std::max(f.u, -A.limx), A.limx);
    f.vc = std::min(std::max(f.v, -A.limy), A.limy);
    for (int r = 0; r < 3; ++r)
        for (int j = 0; j < 3; ++j) f.M[3 * r + j] = f.Rc[3 * r + j] * f.se[j];
    const D ax = fx / f.zs, ay = fy / f.zs;
    for (int j = 0; j < 3; ++j) {
        f.r0[j] = ax * (f.M[j] - f.uc * f.M[6 + j]);
        f.r1[j] = ay * (f.M[3 + j] - f.vc * f.M[6 + j]);
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
    f.fac = 1.0;
    f.okk = false;
    if (kk > 0) {
        f.det0 = f.gdet + eps * (f.a0 + f.c0) + eps * eps;
        f.okk = f.det > 0 && f.det0 > 0 && !f.culled;
        f.fac = f.okk ? std::sqrt(f.det0 / f.det) : 0.0;
        f.o2 = f.o1 * f.fac;
    }
    f.ok = f.det > 0 && !f.culled;
    if (f.ok) {
        f.conic[0] = f.c / f.det;
        f.conic[1] = -f.b / f.det;
        f.conic[2] = f.a / f.det;
    } else {  // as the PyTorch path (never read: such Gaussians are not binned)
        f.conic[0] = f.c;
        f.conic[1] = -f.b;
        f.conic[2] = f.a;
    }

    if constexpr (KER == K_EWA) {
        int idx = 0;  // argmin, first index on ties
        if (f.se[1] < f.se[idx]) idx = 1;
        if (f.se[2] < f.se[idx]) idx = 2;
        f.idx = idx;
        const D nd = f.Rc[idx] * f.mu[0] + f.Rc[3 + idx] * f.mu[1] + f.Rc[6 + idx] * f.mu[2];
        f.sgn = nd > 0 ? -1.0 : 1.0;
    } else {
        f.dc[0] = f.uc, f.dc[1] = f.vc, f.dc[2] = 1.0;
        f.dm = 0;
        for (int j = 0; j < 3; ++j) {
            f.dt[j] = (f.dc[0] * f.Rc[j] + f.dc[1] * f.Rc[3 + j] + f.dc[2] * f.Rc[6 + j]) / f.se[j];
            f.dm += f.dt[j] * f.dt[j];
            f.h[j] = f.dt[j] / f.se[j];
        }
        for (int r = 0; r < 3; ++r) f.mvec[r] = f.Rc[3 * r] * f.h[0] + f.Rc[3 * r + 1] * f.h[1] + f.Rc[3 * r + 2] * f.h[2];
        f.nn2 = f.uc * f.uc + f.vc * f.vc + 1.0;
        f.sq = std::sqrt(f.nn2);
        f.lc = f.zs * f.sq;
        f.dms = f.culled ? 1.0 : f.dm;
        f.p0 = -f.lc * (f.mvec[0] / f.dms - f.uc / f.nn2);
        f.p1 = -f.lc * (f.mvec[1] / f.dms - f.vc / f.nn2);
        for (int j = 0; j < 3; ++j) {
            f.mut[j] = (f.mu[0] * f.Rc[j] + f.mu[1] * f.Rc[3 + j] + f.mu[2] * f.Rc[6 + j]) / f.se[j];
            f.w[j] = f.mut[j] / f.se[j];
        }
        for (int r = 0; r < 3; ++r) f.bvec[r] = f.Rc[3 * r] * f.w[0] + f.Rc[3 * r + 1] * f.w[1] + f.Rc[3 * r + 2] * f.w[2];
        f.l = std::sqrt(f.mu[0] * f.mu[0] + f.mu[1] * f.mu[1] + f.mu[2] * f.mu[2]);
        f.bnorm = std::sqrt(f.bvec[0] * f.bvec[0] + f.bvec[1] * f.bvec[1] + f.bvec[2] * f.bvec[2]);
        f.bden = std::max(f.bnorm, 1e-12);
        for (int r = 0; r < 3; ++r) f.nrm[r] = -f.bvec[r] / f.bden;
    }
}

inline D clampd(D x, D lo, D hi) { return std::min(std::max(x, lo), hi); }

template <typename T, int KER>
void project_forward(const ProjArgs& A) {
    constexpr int P = KER == K_EWA ? 13 : 15;
    const D ts = (D)A.tile, gx = (D)A.gx, gy = (D)A.gy;
#pragma omp parallel for num_threads((int)A.nthreads) schedule(static, 1024)
    for (int64_t i = 0; i < A.n; ++i) {
        Fw f;
        forward_one<T, KER>(A, i, f);
        T* p = (T*)A.params + i * P;
        const D mx = A.fx * f.u + A.cx, my = A.fy * f.v + A.cy;
        p[0] = (T)mx;
        p[1] = (T)my;
        p[2] = (T)f.conic[0];
        p[3] = (T)f.conic[1];
        p[4] = (T)f.conic[2];
        p[5] = (T)(f.ok ? f.o2 : 0.0);
        p[6] = (T)f.rgb[0];
        p[7] = (T)f.rgb[1];
        p[8] = (T)f.rgb[2];
        if constexpr (KER == K_EWA) {
            p[9] = (T)f.z;
            p[10] = (T)(f.sgn * f.Rc[f.idx]);
            p[11] = (T)(f.sgn * f.Rc[3 + f.idx]);
            p[12] = (T)(f.sgn * f.Rc[6 + f.idx]);
        } else {
            p[9] = (T)f.l;
            p[10] = (T)(f.p0 / A.fx);
            p[11] = (T)(f.p1 / A.fy);
            p[12] = (T)f.nrm[0];
            p[13] = (T)f.nrm[1];
            p[14] = (T)f.nrm[2];
        }
        // radius, alpha-support box, tile rectangles (no gradient)
        const D mid = 0.5 * (f.a + f.c);
        const D lam = mid + std::sqrt(std::max(mid * mid - f.det, 0.1));
        const D radius = f.ok ? std::ceil(3.0 * std::sqrt(std::max(lam, 0.0))) : 0.0;
        const D tau = std::log(std::max(255.0 * f.o1, 1e-30));
        D bnd[4];
        if (tau > 0) {
            const D t2 = 2.0 * tau;
            const D hx = std::sqrt(t2 * f.a) * 1.001 + 0.01, hy = std::sqrt(t2 * f.c) * 1.001 + 0.01;
            bnd[0] = mx - hx, bnd[1] = mx + hx, bnd[2] = my - hy, bnd[3] = my + hy;
        } else {
            bnd[0] = BIGV, bnd[1] = -BIGV, bnd[2] = BIGV, bnd[3] = -BIGV;
        }
        for (int k = 0; k < 4; ++k) bnd[k] = clampd(bnd[k], -BIGV, BIGV);
        const D rr[4] = {
            clampd(std::floor((mx - radius) / ts), 0, gx), clampd(std::floor((mx + radius + ts - 1) / ts), 0, gx),
            clampd(std::floor((my - radius) / ts), 0, gy), clampd(std::floor((my + radius + ts - 1) / ts), 0, gy)};
        const D rb[4] = {
            clampd(std::floor((bnd[0] - 0.5) / ts), 0, gx), clampd(std::floor((bnd[1] - 0.5) / ts) + 1, 0, gx),
            clampd(std::floor((bnd[2] - 0.5) / ts), 0, gy), clampd(std::floor((bnd[3] - 0.5) / ts) + 1, 0, gy)};
        const bool vis = f.ok && radius > 0 && (rr[1] - rr[0]) * (rr[3] - rr[2]) > 0;
        D rc[4] = {std::max(rr[0], rb[0]), std::min(rr[1], rb[1]), std::max(rr[2], rb[2]), std::min(rr[3], rb[3])};
        rc[1] = std::max(rc[1], rc[0]);
        rc[3] = std::max(rc[3], rc[2]);
        int32_t* rect = A.rect + 4 * i;
        int32_t* rrad = A.rect_radius + 4 * i;
        for (int k = 0; k < 4; ++k) {
            rect[k] = vis ? (int32_t)rc[k] : 0;
            rrad[k] = vis ? (int32_t)rr[k] : 0;
        }
        A.radii[i] = vis ? (int64_t)radius : 0;
        A.visible[i] = vis ? 1 : 0;
        T* m2 = (T*)A.means2d + 2 * i;
        m2[0] = f.ok ? (T)mx : T(0);
        m2[1] = f.ok ? (T)my : T(0);
        ((T*)A.depth)[i] = (T)f.z;
        T* bo = (T*)A.bounds + 4 * i;
        for (int k = 0; k < 4; ++k) bo[k] = (T)bnd[k];
    }
}

template <typename T, int KER>
void project_backward(const ProjArgs& A) {
    constexpr int P = KER == K_EWA ? 13 : 15;
    const D fx = A.fx, fy = A.fy;
#pragma omp parallel for num_threads((int)A.nthreads) schedule(static, 1024)
    for (int64_t i = 0; i < A.n; ++i) {
        Fw f;
        forward_one<T, KER>(A, i, f);
        const T* gp = (const T*)A.g_params + i * P;
        D g[P];
        for (int k = 0; k < P; ++k) g[k] = (D)gp[k];
        D gmu[3] = {0, 0, 0}, gRc[9] = {0, 0, 0, 0, 0, 0, 0, 0, 0}, gse[3] = {0, 0, 0}, gm[3] = {0, 0, 0};
        D guc = 0, gvc = 0, gu = 0, gv = 0, gzs = 0;

        // SH colour
        const int deg = (int)A.sh_degree;
        const T* sh = (const T*)A.sh + i * A.sh_k * 3;
        T* gsh = (T*)A.g_sh + i * A.sh_k * 3;
        D graw[3];
        for (int ch = 0; ch < 3; ++ch) graw[ch] = (f.raw[ch] + 0.5 >= 0.0) ? g[6 + ch] : 0.0;
        if (deg == 0) {
            for (int ch = 0; ch < 3; ++ch) gsh[ch] = (T)(SH0 * graw[ch]);
        } else {
            D bs[16], db[16][3];
            sh_basis(deg, f.dir[0], f.dir[1], f.dir[2], bs, db);
            const int nb = (deg + 1) * (deg + 1);
            D gdir[3] = {0, 0, 0};
            for (int k = 0; k < nb; ++k) {
                D s = 0;
                for (int ch = 0; ch < 3; ++ch) {
                    gsh[3 * k + ch] = (T)(bs[k] * graw[ch]);
                    s += (D)sh[3 * k + ch] * graw[ch];
                }
                gdir[0] += db[k][0] * s;
                gdir[1] += db[k][1] * s;
                gdir[2] += db[k][2] * s;
            }
            if (f.dn >= 1e-12) {
                const D pr = f.dir[0] * gdir[0] + f.dir[1] * gdir[1] + f.dir[2] * gdir[2];
                for (int k = 0; k < 3; ++k) gm[k] += (gdir[k] - f.dir[k] * pr) / f.dden;
            } else {
                for (int k = 0; k < 3; ++k) gm[k] += gdir[k] / f.dden;
            }
        }

        // means2d = (fx u + cx, fy v + cy)
        gu += fx * g[0];
        gv += fy * g[1];

        // kernel extras
        if constexpr (KER == K_EWA) {
            gmu[2] += g[9];
            gRc[f.idx] += f.sgn * g[10];
            gRc[3 + f.idx] += f.sgn * g[11];
            gRc[6 + f.idx] += f.sgn * g[12];
        } else {
            // l = |mu|
            if (f.l > 0)
                for (int k = 0; k < 3; ++k) gmu[k] += g[9] * f.mu[k] / f.l;
            // nrm = -normalize(bvec)
            D gbv[3];
            {
                const D gbh[3] = {-g[12], -g[13], -g[14]};
                if (f.bnorm >= 1e-12) {
                    const D bh[3] = {f.bvec[0] / f.bden, f.bvec[1] / f.bden, f.bvec[2] / f.bden};
                    const D pr = bh[0] * gbh[0] + bh[1] * gbh[1] + bh[2] * gbh[2];
                    for (int k = 0; k < 3; ++k) gbv[k] = (gbh[k] - bh[k] * pr) / f.bden;
                } else {
                    for (int k = 0; k < 3; ++k) gbv[k] = gbh[k] / f.bden;
                }
            }
            // bvec_r = Σ_j Rc_rj w_j, w_j = mut_j / se_j, mut_j = (Σ_r mu_r Rc_rj) / se_j
            for (int j = 0; j < 3; ++j) {
                D gw = 0;
                for (int r = 0; r < 3; ++r) {
                    gRc[3 * r + j] += gbv[r] * f.w[j];
                    gw += f.Rc[3 * r + j] * gbv[r];
                }
                const D gmut = gw / f.se[j];
                gse[j] -= gw * f.w[j] / f.se[j];
                const D gy = gmut / f.se[j];
                gse[j] -= gmut * f.mut[j] / f.se[j];
                for (int r = 0; r < 3; ++r) {
                    gmu[r] += f.Rc[3 * r + j] * gy;
                    gRc[3 * r + j] += f.mu[r] * gy;
                }
            }
            // p0 = -lc (mvec0/dms - uc/nn2), p1 likewise; payload p/f
            const D gp0 = g[10] / fx, gp1 = g[11] / fy;
            const D e0 = f.mvec[0] / f.dms - f.uc / f.nn2, e1 = f.mvec[1] / f.dms - f.vc / f.nn2;
            const D glc = -e0 * gp0 - e1 * gp1;
            const D gmv[3] = {-f.lc / f.dms * gp0, -f.lc / f.dms * gp1, 0.0};
            const D gdms = f.lc * (f.mvec[0] * gp0 + f.mvec[1] * gp1) / (f.dms * f.dms);
            guc += f.lc / f.nn2 * gp0;
            gvc += f.lc / f.nn2 * gp1;
            D gnn2 = -f.lc * (f.uc * gp0 + f.vc * gp1) / (f.nn2 * f.nn2);
            // lc = zs sqrt(nn2)
            gzs += glc * f.sq;
            gnn2 += glc * f.zs / (2.0 * f.sq);
            guc += 2.0 * f.uc * gnn2;
            gvc += 2.0 * f.vc * gnn2;
            const D gdm = f.culled ? 0.0 : gdms;
            // mvec_r = Σ_j Rc_rj h_j, h_j = dt_j/se_j; dm = Σ dt_j², dt_j = (Σ_r dc_r Rc_rj)/se_j
            D gdc[3] = {0, 0, 0};
            for (int j = 0; j < 3; ++j) {
                D gh = 0;
                for (int r = 0; r < 3; ++r) {
                    gRc[3 * r + j] += gmv[r] * f.h[j];
                    gh += f.Rc[3 * r + j] * gmv[r];
                }
                D gdt = gh / f.se[j] + 2.0 * f.dt[j] * gdm;
                gse[j] -= gh * f.h[j] / f.se[j];
                const D ge = gdt / f.se[j];
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
        D ga = 0, gb = 0, gc = 0, gdet = 0, gdet0 = 0, go1 = 0;
        const D go2 = f.ok ? g[5] : 0.0;
        if (kk > 0) {
            go1 += go2 * f.fac;
            if (f.okk) {
                const D gfac = go2 * f.o1;
                gdet0 += gfac * f.fac / (2.0 * f.det0);
                gdet -= gfac * f.fac / (2.0 * f.det);
            }
        } else {
            go1 += go2;
        }
        if (f.ok) {
            // X = S⁻¹ = [[A, B], [B, C]]; dL/dS = -X G X with G = [[gA, gB/2], [gB/2, gC]]
            const D XA = f.conic[0], XB = f.conic[1], XC = f.conic[2];
            const D GA = g[2], GB = 0.5 * g[3], GC = g[4];
            // XG
            const D t00 = XA * GA + XB * GB, t01 = XA * GB + XB * GC;
            const D t10 = XB * GA + XC * GB, t11 = XB * GB + XC * GC;
            const D y00 = t00 * XA + t01 * XB, y01 = t00 * XB + t01 * XC, y11 = t10 * XB + t11 * XC;
            ga -= y00;
            gc -= y11;
            gb -= 2.0 * y01;
        } else {
            ga += g[4];
            gb -= g[3];
            gc += g[2];
        }
        // a = a0 + e1, c = c0 + e1, det = gdet + e1 (a0 + c0) + e1², det0 = gdet + eps (a0 + c0) + eps²
        const D ga0 = ga + gdet * e1 + gdet0 * eps;
        const D gc0 = gc + gdet * e1 + gdet0 * eps;
        const D ggd = gdet + gdet0;
        D gr0[3], gr1[3];
        {
            const D gcr[3] = {2.0 * ggd * f.cr[0], 2.0 * ggd * f.cr[1], 2.0 * ggd * f.cr[2]};
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
        D gM[9];
        {
            const D ax = fx / f.zs, ay = fy / f.zs;
            D s0 = 0, s1 = 0, sr0 = 0, sr1 = 0;
            for (int j = 0; j < 3; ++j) {
                gM[j] = ax * gr0[j];
                gM[3 + j] = ay * gr1[j];
                gM[6 + j] = -ax * f.uc * gr0[j] - ay * f.vc * gr1[j];
                s0 += f.M[6 + j] * gr0[j];
                s1 += f.M[6 + j] * gr1[j];
                sr0 += f.r0[j] * gr0[j];
                sr1 += f.r1[j] * gr1[j];
            }
            guc -= ax * s0;
            gvc -= ay * s1;
            gzs -= (sr0 + sr1) / f.zs;
        }
        // clamp, u = mu0/zs, v = mu1/zs
        if (f.inx) gu += guc;
        if (f.iny) gv += gvc;
        gmu[0] += gu / f.zs;
        gmu[1] += gv / f.zs;
        gzs -= (f.u * gu + f.v * gv) / f.zs;
        if (!f.culled) gmu[2] += gzs;
        // M = Rc diag(se)
        for (int r = 0; r < 3; ++r)
            for (int j = 0; j < 3; ++j) {
                gRc[3 * r + j] += gM[3 * r + j] * f.se[j];
                gse[j] += gM[3 * r + j] * f.Rc[3 * r + j];
            }
        // Rc = rotmat(qc)
        D gqc[4];
        {
            const D w = f.qc[0], x = f.qc[1], y = f.qc[2], z = f.qc[3];
            const D* G = gRc;
            gqc[0] = 2.0 * (-z * G[1] + y * G[2] + z * G[3] - x * G[5] - y * G[6] + x * G[7]);
            gqc[1] = 2.0 * (-2.0 * x * G[4] - 2.0 * x * G[8] + y * G[1] + z * G[2] + y * G[3] - w * G[5] + z * G[6] + w * G[7]);
            gqc[2] = 2.0 * (-2.0 * y * G[0] - 2.0 * y * G[8] + x * G[1] + w * G[2] + x * G[3] + z * G[5] - w * G[6] + z * G[7]);
            gqc[3] = 2.0 * (-2.0 * z * G[0] - 2.0 * z * G[4] - w * G[1] + x * G[2] + w * G[3] + y * G[5] + x * G[6] + y * G[7]);
        }
        // qc = L q; q = qr / max(|qr|, 1e-12)
        D gq[4];
        for (int k = 0; k < 4; ++k) gq[k] = A.L[k] * gqc[0] + A.L[4 + k] * gqc[1] + A.L[8 + k] * gqc[2] + A.L[12 + k] * gqc[3];
        T* gQ = (T*)A.g_quats + 4 * i;
        if (f.qn >= 1e-12) {
            const D pr = f.q[0] * gq[0] + f.q[1] * gq[1] + f.q[2] * gq[2] + f.q[3] * gq[3];
            for (int k = 0; k < 4; ++k) gQ[k] = (T)((gq[k] - f.q[k] * pr) / f.qden);
        } else {
            for (int k = 0; k < 4; ++k) gQ[k] = (T)(gq[k] / f.qden);
        }
        // mu = R m + t
        for (int k = 0; k < 3; ++k) gm[k] += A.R[k] * gmu[0] + A.R[3 + k] * gmu[1] + A.R[6 + k] * gmu[2];
        T* gM_out = (T*)A.g_means + 3 * i;
        for (int k = 0; k < 3; ++k) gM_out[k] = (T)gm[k];
        // 3D filter: se = sqrt(s² + f3), o1 = o sqrt(Π s²/(s² + f3))
        T* gS = (T*)A.g_scales + 3 * i;
        if (A.has_filter) {
            const D gfo = go1 * f.o;
            for (int k = 0; k < 3; ++k) {
                const D gs2f = gse[k] / (2.0 * f.se[k]) - gfo * f.fo / (2.0 * f.s2f[k]);
                gS[k] = (T)(2.0 * f.s[k] * gs2f + gfo * f.fo / f.s[k]);
            }
            ((T*)A.g_opac)[i] = (T)(go1 * f.fo);
        } else {
            for (int k = 0; k < 3; ++k) gS[k] = (T)gse[k];
            ((T*)A.g_opac)[i] = (T)go1;
        }
    }
}

template <typename T>
int run(const ProjArgs& A, bool fwd) {
    if (A.kernel == K_EWA) {
        if (fwd) project_forward<T, K_EWA>(A);
        else project_backward<T, K_EWA>(A);
    } else if (A.kernel == K_RADE) {
        if (fwd) project_forward<T, K_RADE>(A);
        else project_backward<T, K_RADE>(A);
    } else {
        return -1;
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
