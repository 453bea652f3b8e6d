// NeuSG's multi-resolution dense grid encoding (methods/neusg_field.py `MultiGrid`): trilinear interpolation of
// each level's feature grid at points in [0, 1]³, and its backward with respect to the grids, float32 and float64.
// Python API and the PyTorch reference (torch.nn.functional.grid_sample, align_corners=True, padding_mode="border"):
// methods/neusg_grid.py; tests: tests/test_neusg_grid.py. Plain C ABI, OpenMP.
//
// Level l has resolution N = res[l] (>= 1): a grid (F, N+1, N+1, N+1), C-contiguous, indexed [f, z, y, x], vertex i at
// i / N. For a point u (3 coordinates, u_0 → x, u_1 → y, u_2 → z), per axis
//   s = min(max(u N, 0), N),   i = min(floor(s), N − 1),   t = s − i      (border padding: s clamped to the grid)
// and the feature is the trilinear blend of the cell's 8 vertices,
//   out[p, l·F + f] = Σ_{a,b,c ∈ {0,1}} w_x^a w_y^b w_z^c · grid_l[f, i_z + c, i_y + b, i_x + a],
//   w^0 = 1 − t, w^1 = t,
// which is grid_sample's value (its corner i + 1 at s = N lies outside and weighs t − 0 = 0; here i = N − 1 and the
// corner N weighs 1: the same sum). The backward is the transpose: g_grid_l[f, corner] += w · g_out[p, l·F + f].
// All arithmetic in float64 whatever the storage type T; results rounded once on store. The backward accumulates
// into the gradient (stored in T) in increasing point order, each level by one thread (OpenMP over levels), so it is
// bitwise the same for any thread count (training resumes exactly). The gradient of the points is not computed
// (the Python side routes points that require one to the reference).
//
// A non-finite coordinate cannot index outside a grid: the cell index is clamped as an integer after conversion.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <omp.h>

#include "neusg_cell.h"

namespace {


// The cell's 8 vertex offsets (in the level's flattened (N+1)³ index) and weights, corner (a, b, c) at a + 2b + 4c.
inline void corners(const double* u, int64_t n, int64_t* offset, double* weight) {
    const Axis x = axis(u[0], n), y = axis(u[1], n), z = axis(u[2], n);
    const int64_t side = n + 1;
    const int64_t base = (z.i * side + y.i) * side + x.i;
    const double wx[2] = {1.0 - x.t, x.t}, wy[2] = {1.0 - y.t, y.t}, wz[2] = {1.0 - z.t, z.t};
    for (int c = 0; c < 2; ++c)
        for (int b = 0; b < 2; ++b)
            for (int a = 0; a < 2; ++a) {
                const int k = a + 2 * b + 4 * c;
                offset[k] = base + (c * side + b) * side + a;
                weight[k] = wx[a] * wy[b] * wz[c];
            }
}

template <class T>
void forward(int64_t levels, const int64_t* res, int64_t features, int64_t n_points, const void* const* grids,
             const T* unit, T* out, int threads) {
    const int64_t width = levels * features;
#pragma omp parallel for num_threads(threads) schedule(static) if (n_points >= MIN_PARALLEL)
    for (int64_t p = 0; p < n_points; ++p) {
        const double u[3] = {double(unit[3 * p]), double(unit[3 * p + 1]), double(unit[3 * p + 2])};
        for (int64_t l = 0; l < levels; ++l) {
            const int64_t n = res[l], volume = (n + 1) * (n + 1) * (n + 1);
            int64_t offset[8];
            double weight[8];
            corners(u, n, offset, weight);
            const T* grid = (const T*)grids[l];
            for (int64_t f = 0; f < features; ++f) {
                const T* g = grid + f * volume;
                double acc = 0.0;
                for (int k = 0; k < 8; ++k) acc += weight[k] * double(g[offset[k]]);
                out[p * width + l * features + f] = T(acc);
            }
        }
    }
}

template <class T>
void backward(int64_t levels, const int64_t* res, int64_t features, int64_t n_points, const T* unit, const T* g_out,
              void* const* g_grids, int threads) {
    const int64_t width = levels * features;
#pragma omp parallel for num_threads(threads) schedule(static, 1) if (n_points >= MIN_PARALLEL)
    for (int64_t l = 0; l < levels; ++l) {
        const int64_t n = res[l], volume = (n + 1) * (n + 1) * (n + 1);
        T* grad = (T*)g_grids[l];
        std::memset(grad, 0, sizeof(T) * size_t(features * volume));
        for (int64_t p = 0; p < n_points; ++p) {
            const double u[3] = {double(unit[3 * p]), double(unit[3 * p + 1]), double(unit[3 * p + 2])};
            int64_t offset[8];
            double weight[8];
            corners(u, n, offset, weight);
            for (int64_t f = 0; f < features; ++f) {
                const double g = double(g_out[p * width + l * features + f]);
                T* gf = grad + f * volume;
                for (int k = 0; k < 8; ++k) gf[offset[k]] += T(weight[k] * g);
            }
        }
    }
}

}  // namespace

extern "C" {

// dtype: 0 float32, 1 float64. Returns 0, or -1 for a resolution < 1.
int gs_grid_forward(int64_t levels, const int64_t* res, int64_t features, int64_t n_points, int64_t dtype,
                    const void* const* grids, const void* unit, void* out, int64_t threads) {
    for (int64_t l = 0; l < levels; ++l)
        if (res[l] < 1) return -1;
    if (dtype == 0)
        forward(levels, res, features, n_points, grids, (const float*)unit, (float*)out, (int)threads);
    else
        forward(levels, res, features, n_points, grids, (const double*)unit, (double*)out, (int)threads);
    return 0;
}

// g_grids: one gradient per level, the grid's shape; written (zeroed, then accumulated).
int gs_grid_backward(int64_t levels, const int64_t* res, int64_t features, int64_t n_points, int64_t dtype,
                     const void* unit, const void* g_out, void* const* g_grids, int64_t threads) {
    for (int64_t l = 0; l < levels; ++l)
        if (res[l] < 1) return -1;
    if (dtype == 0)
        backward(levels, res, features, n_points, (const float*)unit, (const float*)g_out, g_grids, (int)threads);
    else
        backward(levels, res, features, n_points, (const double*)unit, (const double*)g_out, g_grids, (int)threads);
    return 0;
}

}  // extern "C"
