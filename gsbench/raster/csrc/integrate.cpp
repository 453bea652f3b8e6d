// GOF opacity field at 3D points, all views in one call (no gradient). docs/methods/gof.md §7.1; reference:
// `integrate_reference`. In view v a point x (world) with camera coordinates x_c = R x + t sees every
// Gaussian binned to the tile of its pixel (floor(u), floor(v)), u = fx·x_c/z + cx, v = fy·y_c/z + cy,
// if near < z and (u, v) ∈ [0, W) × [0, H). Each Gaussian is evaluated on the point's exact ray
// r = x_c/z (r_z = 1) at t = min(t*, z):
//   q(t) = q_min + (rᵀAr)(t − t*)²  (exact for the quadratic; no cancellation),
// alpha = min(0.99, o·exp(−q/2)), skipped if < 1/255 or t* <= near; O_v = 1 − Π(1 − alpha).
// The output is m = min(cap, min_v O_v) (views that do not see x are ignored; cap = 1 gives GOF's O).
//
// Per view the tile lists are refined into cells of `cell` × `cell` pixels (`cell` divides the tile
// size, so a cell lies in one tile): a cell keeps, in order, the Gaussians of its tile whose pixel box
// of alpha >= 1/255 (`Projection.bounds`, conservative, continuous pixel coordinates) meets the cell.
// A dropped Gaussian has alpha < 1/255 on every ray through the cell, so the result is unchanged.
//
// Exact early exits (m is bit-identical to evaluating every Gaussian of every view, the minimum
// being independent of the order of the views):
// * within a view, 1 − T only grows as Gaussians are added (T·(1 − α) <= T also after rounding), so
//   the view stops as soon as 1 − T >= m: it can no longer lower the minimum;
// * across views, the loop stops once m < stop_below (sign queries: O < level is then decided);
// * a Gaussian is skipped before the division and the exp when q·rᵀAr > (2 ln(255 o) + 0.01)·rᵀAr,
//   i.e. alpha < exp(−0.005)/255 < 1/255 (the 0.01 margin covers the rounding of q), computed
//   division-free: q·rᵀAr = c·(ΔᵀMΔ + [z < t*]·(z·rᵀAr − b·r)²). Column 24 of the payload holds
//   2 ln(255 o) + 0.01 (integrate.py appends it).
//
// Loop order and threads: see `integrate_impl`.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <omp.h>
#include <vector>

extern "C" {
struct GsCellArgs {
    int64_t width, height, tile_size, cell, nthreads;
    const int32_t* tile_offsets;  // (tiles + 1)
    const int32_t* tile_list;
    const double* bounds;         // (N, 4) xmin, xmax, ymin, ymax pixel box of alpha >= 1/255
    int32_t* cell_offsets;        // (cells + 1) out
    int32_t* cell_list;           // out; null: only count (cell_offsets[-1] = total)
};

struct GsIntArgs {
    int64_t n_points, n_views, n_params, dtype, nthreads, cell;
    double near_z, cap, stop_below;
    const double* cams;        // (V, 16): R row-major (9), t (3), fx, fy, cx, cy
    const int64_t* dims;       // (V, 3): width, height, cells_x
    const int64_t* view_ptrs;  // (V, 3): addresses of params (N, n_params), cell_offsets (cells + 1), cell_list
    const double* points;      // (P, 3) world coordinates
    double* out;               // (P,) m
};
}

namespace {
constexpr int PRESKIP = 24;  // payload column of 2 ln(255 o) + 0.01

struct Ray {
    int cell;  // -1: not seen by the view
    double rx, ry, z;
};

inline Ray project_point(const double* c, const int64_t* d, const double* x, double near_z, int64_t cs) {
    const double xc = c[0] * x[0] + c[1] * x[1] + c[2] * x[2] + c[9];
    const double yc = c[3] * x[0] + c[4] * x[1] + c[5] * x[2] + c[10];
    const double z = c[6] * x[0] + c[7] * x[1] + c[8] * x[2] + c[11];
    if (!(z > near_z)) return {-1, 0.0, 0.0, 1.0};
    const double rx = xc / z, ry = yc / z;
    const double u = c[12] * rx + c[14], v = c[13] * ry + c[15];
    if (!(u >= 0.0 && u < (double)d[0] && v >= 0.0 && v < (double)d[1])) return {-1, 0.0, 0.0, 1.0};
    const int64_t tx = std::min<int64_t>((int64_t)std::floor(u), d[0] - 1) / cs;
    const int64_t ty = std::min<int64_t>((int64_t)std::floor(v), d[1] - 1) / cs;
    return {(int)(ty * d[2] + tx), rx, ry, z};
}

// 1 − T after the Gaussians of `cell`, or any value >= m as soon as 1 − T >= m (the view cannot lower m).
template <typename T>
double view_opacity(const T* P, int64_t np, const int32_t* offsets, const int32_t* list, int cell, T rx, T ry,
                    T zp, T nearz, double m) {
    T trans = T(1);
    for (int k = offsets[cell]; k < offsets[cell + 1]; ++k) {
        const T* p = P + (int64_t)list[k] * np;
        const T* q = p + 9;
        const T Ar0 = q[0] * rx + q[1] * ry + q[2];
        const T Ar1 = q[1] * rx + q[3] * ry + q[4];
        const T Ar2 = q[2] * rx + q[4] * ry + q[5];
        const T rAr = rx * Ar0 + ry * Ar1 + Ar2;
        const T br = q[6] * rx + q[7] * ry + q[8];
        const T Dx = rx - q[13], Dy = ry - q[14];
        const T num = std::max(q[9] * Dx * Dx + T(2) * q[10] * Dx * Dy + q[11] * Dy * Dy, T(0));
        const T behind = zp * rAr - br;  // < 0 iff z < t*
        const T e = behind < T(0) ? num + behind * behind : num;
        if (rAr > T(0) && q[12] * e > p[PRESKIP] * rAr) continue;
        const T ts = br / rAr;
        if (!(ts > nearz)) continue;
        T qq = q[12] * num / rAr;
        if (zp < ts) {
            const T dt = zp - ts;
            qq += q[12] * rAr * dt * dt;
        }
        const T al = std::min(T(0.99), p[5] * std::exp(T(-0.5) * qq));
        if (al < T(1.0 / 255.0)) continue;
        trans *= T(1) - al;
        if ((double)(T(1) - trans) >= m) break;
    }
    return (double)(T(1) - trans);
}

// Undecided points [lo, hi) seen by view v, bucketed by cell: (order, bucket starts), counting sort.
void bucket_points(const GsIntArgs& a, int64_t lo, int64_t hi, int64_t v, std::vector<int32_t>& cell,
                   std::vector<int32_t>& order, std::vector<int32_t>& start) {
    const int64_t* d = a.dims + 3 * v;
    const int64_t ncell = d[2] * ((d[1] + a.cell - 1) / a.cell);
    start.assign(ncell + 1, 0);
    for (int64_t i = lo; i < hi; ++i) {
        const bool active = !(a.out[i] < a.stop_below);
        cell[i - lo] = active ? project_point(a.cams + 16 * v, d, a.points + 3 * i, a.near_z, a.cell).cell : -1;
        if (cell[i - lo] >= 0) ++start[cell[i - lo] + 1];
    }
    for (int64_t c = 0; c < ncell; ++c) start[c + 1] += start[c];
    std::vector<int32_t> fill(start.begin(), start.end() - 1);
    for (int64_t i = lo; i < hi; ++i)
        if (cell[i - lo] >= 0) order[fill[cell[i - lo]]++] = (int32_t)i;
}

// One block of points [lo, hi): views outer, then cells, then the block's points in the cell, so the
// view's payload rows and the cell's list stay in cache.
template <typename T>
void integrate_block(const GsIntArgs& a, int64_t lo, int64_t hi) {
    std::vector<int32_t> cell(hi - lo), order(hi - lo), start;
    for (int64_t v = 0; v < a.n_views; ++v) {
        bucket_points(a, lo, hi, v, cell, order, start);
        const int64_t* vp = a.view_ptrs + 3 * v;
        const T* params = (const T*)vp[0];
        const int32_t *offsets = (const int32_t*)vp[1], *list = (const int32_t*)vp[2];
        for (int64_t c = 0; c + 1 < (int64_t)start.size(); ++c) {
            for (int32_t k = start[c]; k < start[c + 1]; ++k) {
                const int32_t i = order[k];
                const Ray r = project_point(a.cams + 16 * v, a.dims + 3 * v, a.points + 3 * i, a.near_z, a.cell);
                const double ov = view_opacity<T>(params, a.n_params, offsets, list, (int)c, (T)r.rx, (T)r.ry, (T)r.z,
                                                  (T)a.near_z, a.out[i]);
                a.out[i] = std::min(a.out[i], ov);
            }
        }
    }
}

// Threads take blocks of points (dynamic): one parallel region per call, no barrier per view (the
// machine is shared; a barrier per view costs a time slice when the cores are oversubscribed).
template <typename T>
void integrate_impl(const GsIntArgs& a) {
    const int64_t P = a.n_points;
    std::fill(a.out, a.out + P, a.cap);
    const int64_t block = std::clamp<int64_t>(P / (8 * a.nthreads), 256, 8192);
#pragma omp parallel for num_threads((int)a.nthreads) schedule(dynamic, 1)
    for (int64_t lo = 0; lo < P; lo += block)
        integrate_block<T>(a, lo, std::min(P, lo + block));
}

// Cell lists of one view (see the header): count pass (cell_list null) or fill pass.
void cell_lists(const GsCellArgs& a) {
    const int64_t cs = a.cell, cx = (a.width + cs - 1) / cs, cy = (a.height + cs - 1) / cs;
    const int64_t tiles_x = (a.width + a.tile_size - 1) / a.tile_size;
    if (!a.cell_list) a.cell_offsets[0] = 0;
#pragma omp parallel for num_threads((int)a.nthreads) schedule(dynamic, 16)
    for (int64_t c = 0; c < cx * cy; ++c) {
        const int64_t x = c % cx, y = c / cx;
        const double x0 = (double)(x * cs), x1 = (double)std::min((x + 1) * cs, a.width);
        const double y0 = (double)(y * cs), y1 = (double)std::min((y + 1) * cs, a.height);
        const int64_t tile = (y * cs / a.tile_size) * tiles_x + x * cs / a.tile_size;
        int32_t n = 0;
        int32_t* dst = a.cell_list ? a.cell_list + a.cell_offsets[c] : nullptr;
        for (int k = a.tile_offsets[tile]; k < a.tile_offsets[tile + 1]; ++k) {
            const double* b = a.bounds + 4 * (int64_t)a.tile_list[k];
            if (b[0] > x1 || b[1] < x0 || b[2] > y1 || b[3] < y0) continue;
            if (dst) dst[n] = a.tile_list[k];
            ++n;
        }
        if (!dst) a.cell_offsets[c + 1] = n;
    }
    if (!a.cell_list)
        for (int64_t c = 0; c < cx * cy; ++c) a.cell_offsets[c + 1] += a.cell_offsets[c];
}
}  // namespace

extern "C" int gs_integrate_cells(void* args) {
    cell_lists(*(const GsCellArgs*)args);
    return 0;
}

extern "C" int gs_integrate(void* args) {
    const GsIntArgs& a = *(const GsIntArgs*)args;
    if (a.dtype == 0) integrate_impl<float>(a);
    else integrate_impl<double>(a);
    return 0;
}
