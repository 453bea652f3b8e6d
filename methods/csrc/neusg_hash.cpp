// NeuSG's multiresolution hash encoding (Instant-NGP, Müller et al. 2022, its eqs. 2–4; methods/neusg_field.py
// `HashGrid`): per level a table of feature vectors addressed by the level's grid vertices, trilinear interpolation of
// the 8 vertices of a point's cell, and the backward with respect to the tables, float32 and float64. Python API and the
// PyTorch reference: methods/neusg_hash.py; tests: tests/test_neusg_hash.py. Plain C ABI, OpenMP.
//
// Level l has resolution N = res[l] (>= 1) and a table of T = size[l] rows of F features, C-contiguous (T, F). The
// cell and the weights are those of the dense grid (csrc/neusg_grid.cpp): per axis
//   s = min(max(u N, 0), N),   i = min(floor(s), N − 1),   t = s − i,
//   out[p, l·F + f] = Σ_{a,b,c ∈ {0,1}} w_x^a w_y^b w_z^c · table_l[index(i_x + a, i_y + b, i_z + c), f],
// w^0 = 1 − t, w^1 = t. A vertex (x, y, z) ∈ [0, N]³ is stored at
//   index = x + (N + 1) (y + (N + 1) z)                                   when (N + 1)³ <= T (a dense level),
//   index = (x · 1  ⊕  y · 2654435761  ⊕  z · 805459861) mod T           otherwise (Instant-NGP eq. 4),
// the products and the XOR in unsigned 32-bit arithmetic (wrapping), as Instant-NGP computes them.
// The backward is the transpose, g_table_l[index, f] += w · g_out[p, l·F + f]: all arithmetic in float64 whatever the
// storage type, each level accumulated by one thread (OpenMP over levels) in increasing point order, so the
// gradient is bitwise the same for any thread count (training resumes exactly). The points' gradient is not
// computed: NeuSG's normal is the 4-tap numerical gradient (methods/neusg_field.py `SDFField.with_gradient`).
//
// A non-finite coordinate cannot index outside a table: the cell index is clamped as an integer after conversion.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <omp.h>

#include "neusg_cell.h"

namespace {

constexpr uint32_t PRIME_Y = 2654435761u, PRIME_Z = 805459861u;  // Instant-NGP's π₂, π₃ (π₁ = 1)

inline int64_t vertex_index(int64_t x, int64_t y, int64_t z, int64_t n, int64_t size) {
    const int64_t side = n + 1;
    if (side * side * side <= size) return x + side * (y + side * z);
    const uint32_t h = uint32_t(x) ^ (uint32_t(y) * PRIME_Y) ^ (uint32_t(z) * PRIME_Z);
    return int64_t(h % uint32_t(size));
}

// The cell's 8 table rows and weights, corner (a, b, c) at a + 2b + 4c.
inline void corners(const double* u, int64_t n, int64_t size, int64_t* row, double* weight) {
    const Axis x = axis(u[0], n), y = axis(u[1], n), z = axis(u[2], n);
    const double wx[2] = {1.0 - x.t, x.t}, wy[2] = {1.0 - y.t, y.t}, wz[2] = {1.0 - z.t, z.t};
    for (int c = 0; c < 2; ++c)
        for (int b = 0; b < 2; ++b)
            for (int a = 0; a < 2; ++a) {
                const int k = a + 2 * b + 4 * c;
                row[k] = vertex_index(x.i + a, y.i + b, z.i + c, n, size);
                weight[k] = wx[a] * wy[b] * wz[c];
            }
}

template <class T>
void forward(int64_t levels, const int64_t* res, const int64_t* size, int64_t features, int64_t n_points,
             const void* const* tables, const T* unit, T* out, int threads) {
    const int64_t width = levels * features;
#pragma omp parallel for num_threads(threads) schedule(static) if (n_points >= MIN_PARALLEL)
    for (int64_t p = 0; p < n_points; ++p) {
        const double u[3] = {double(unit[3 * p]), double(unit[3 * p + 1]), double(unit[3 * p + 2])};
        for (int64_t l = 0; l < levels; ++l) {
            int64_t row[8];
            double weight[8];
            corners(u, res[l], size[l], row, weight);
            const T* table = (const T*)tables[l];
            for (int64_t f = 0; f < features; ++f) {
                double acc = 0.0;
                for (int k = 0; k < 8; ++k) acc += weight[k] * double(table[row[k] * features + f]);
                out[p * width + l * features + f] = T(acc);
            }
        }
    }
}

template <class T>
void backward(int64_t levels, const int64_t* res, const int64_t* size, int64_t features, int64_t n_points,
              const T* unit, const T* g_out, void* const* g_tables, int threads) {
    const int64_t width = levels * features;
#pragma omp parallel for num_threads(threads) schedule(static, 1) if (n_points >= MIN_PARALLEL)
    for (int64_t l = 0; l < levels; ++l) {
        T* grad = (T*)g_tables[l];
        std::memset(grad, 0, sizeof(T) * size_t(size[l] * features));
        for (int64_t p = 0; p < n_points; ++p) {
            const double u[3] = {double(unit[3 * p]), double(unit[3 * p + 1]), double(unit[3 * p + 2])};
            int64_t row[8];
            double weight[8];
            corners(u, res[l], size[l], row, weight);
            for (int64_t f = 0; f < features; ++f) {
                const double g = double(g_out[p * width + l * features + f]);
                for (int k = 0; k < 8; ++k) grad[row[k] * features + f] += T(weight[k] * g);
            }
        }
    }
}

bool valid(int64_t levels, const int64_t* res, const int64_t* size) {
    for (int64_t l = 0; l < levels; ++l)
        if (res[l] < 1 || size[l] < 1 || size[l] > (int64_t(1) << 31)) return false;
    return true;
}

}  // namespace

extern "C" {

// dtype: 0 float32, 1 float64. Returns 0, or -1 for a resolution < 1 or a table size outside [1, 2^31].
int gs_hash_forward(int64_t levels, const int64_t* res, const int64_t* size, int64_t features, int64_t n_points,
                    int64_t dtype, const void* const* tables, const void* unit, void* out, int64_t threads) {
    if (!valid(levels, res, size)) return -1;
    if (dtype == 0)
        forward(levels, res, size, features, n_points, tables, (const float*)unit, (float*)out, (int)threads);
    else
        forward(levels, res, size, features, n_points, tables, (const double*)unit, (double*)out, (int)threads);
    return 0;
}

// g_tables: one gradient per level, the table's shape; written (zeroed, then accumulated).
int gs_hash_backward(int64_t levels, const int64_t* res, const int64_t* size, int64_t features, int64_t n_points,
                     int64_t dtype, const void* unit, const void* g_out, void* const* g_tables, int64_t threads) {
    if (!valid(levels, res, size)) return -1;
    if (dtype == 0)
        backward(levels, res, size, features, n_points, (const float*)unit, (const float*)g_out, g_tables,
                 (int)threads);
    else
        backward(levels, res, size, features, n_points, (const double*)unit, (const double*)g_out, g_tables,
                 (int)threads);
    return 0;
}

}  // extern "C"
