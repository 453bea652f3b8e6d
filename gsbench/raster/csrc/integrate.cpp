// GOF opacity field at 3D points for one view (no gradient), GOF doc §1.7 / reference Decision in
// `integrate_reference`: a point sees every Gaussian binned to the tile of its pixel; each is evaluated
// on the point's exact ray r = x_c/z (r_z = 1) at t = min(t*, z):
//   q(t) = q_min + (rᵀAr)(t − t*)²  (exact for the quadratic; no cancellation),
// alpha = min(0.99, o·exp(−q/2)), skipped if < 1/255 or t* <= near; O_v = 1 − Π(1 − alpha).
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <omp.h>

extern "C" {
struct GsIntArgs {
    int64_t n_points, n_params, dtype, nthreads;
    double near_z;
    const void* params;           // (N, P) raymax payload (see projection.py)
    const int32_t* tile_offsets;  // (tiles + 1)
    const int32_t* tile_list;
    const int32_t* point_tile;    // (P,) tile index or -1 (not in view)
    const void* rays;             // (P, 3): rx, ry, z
    void* out;                    // (P,) O_v (1 - prod) ; untouched where point_tile < 0
};
}

namespace {
template <typename T>
void integrate_impl(const GsIntArgs& a) {
    const T* P = (const T*)a.params;
    const T* R = (const T*)a.rays;
    T* out = (T*)a.out;
    const int64_t np = a.n_params;
    const T nearz = (T)a.near_z;
#pragma omp parallel for num_threads((int)a.nthreads) schedule(dynamic, 256)
    for (int64_t i = 0; i < a.n_points; ++i) {
        const int tile = a.point_tile[i];
        if (tile < 0) continue;
        const T rx = R[3 * i], ry = R[3 * i + 1], zp = R[3 * i + 2];
        T trans = T(1);
        for (int k = a.tile_offsets[tile]; k < a.tile_offsets[tile + 1]; ++k) {
            const T* p = P + (int64_t)a.tile_list[k] * np;
            const T o = p[5];
            const T* q = p + 9;
            const T Ar0 = q[0] * rx + q[1] * ry + q[2];
            const T Ar1 = q[1] * rx + q[3] * ry + q[4];
            const T Ar2 = q[2] * rx + q[4] * ry + q[5];
            const T rAr = rx * Ar0 + ry * Ar1 + Ar2;
            const T br = q[6] * rx + q[7] * ry + q[8];
            const T ts = br / rAr;
            if (!(ts > nearz)) continue;
            const T Dx = rx - q[13], Dy = ry - q[14];
            const T num = std::max(q[9] * Dx * Dx + T(2) * q[10] * Dx * Dy + q[11] * Dy * Dy, T(0));
            T qq = q[12] * num / rAr;
            if (zp < ts) {
                const T dt = zp - ts;
                qq += q[12] * rAr * dt * dt;
            }
            const T al = std::min(T(0.99), o * std::exp(T(-0.5) * qq));
            if (al < T(1.0 / 255.0)) continue;
            trans *= T(1) - al;
        }
        out[i] = T(1) - trans;
    }
}
}  // namespace

extern "C" int gs_integrate(void* args) {
    const GsIntArgs& a = *(const GsIntArgs*)args;
    if (a.dtype == 0) integrate_impl<float>(a);
    else integrate_impl<double>(a);
    return 0;
}
