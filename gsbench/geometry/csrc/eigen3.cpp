// Batched symmetric 3×3 eigen-decomposition in float64 with a gap-regularised backward; IBGS local
// covariances, docs/methods/ibgs.md §3.2, §3.3. Python API, reference and
// tests: gsbench/geometry/eigen3.py, tests/test_eigen3.py. Plain C ABI, OpenMP over the N matrices.
//
// Forward, per matrix C (row-major 3×3; S = (C + Cᵀ)/2 is decomposed, so any input is accepted):
//   1. s = max|S_ij|; s = 0 → λ = 0, V = I. The rest works on A = S/s − qI with q = tr(S/s)/3 (no
//      under- or overflow at any scale).
//   2. p = sqrt(‖A‖²_F/6); p <= ISOTROPIC_REL → isotropic: λ1 = λ2 = λ3 = tr(S)/3, V = I.
//   3. Trigonometric eigenvalues of A/p: r = det(A/p)/2 clamped to [−1, 1], φ = acos(r)/3,
//      θ1 = 2cos φ, θ3 = 2cos(φ + 2π/3), θ2 = −θ1 − θ3. Only the "isolated" one, with the larger gap to
//      its neighbour, is used: θ1 if r >= 0, else θ3 (see isolated_eigenvalue). The acos is
//      ill-conditioned only where two eigenvalues meet and then blurs only their split: θ_iso is accurate.
//   4. Isolated eigenvector (Kopp 2008): the largest of the three cross products of rows of
//      (A − pθ_iso I), normalised. Its error is ~ε_mach·‖A‖/gap, and this gap is >= √3·p.
//   5. Deflation: an orthonormal basis (u, w) of v_iso⊥ gives the 2×2 B = [u w]ᵀ A [u w], solved in closed
//      form (see solve_pair): eigenvalues m ± sqrt(h² + B12²), m = (B11 + B22)/2, h = (B11 − B22)/2.
//      The pair's eigenvalues are thereby accurate to ε_mach·‖A‖ (no acos), its eigenvectors orthogonal
//      to v_iso and to each other.
//   6. λ_iso = v_isoᵀ A v_iso (Rayleigh quotient); assemble, sort descending (a swap can only occur at
//      rounding level), set v3 := v1 × v2 (det V = +1), and undo the shift and scale: λ = s(λ_A + q).
// Output: lam (N, 3) descending; V (N, 3, 3) row-major with column k the eigenvector of lam[k].
//
// Backward (exact for λ, gap-regularised for V): with G = Vᵀ gV,
//   M_ij = δ_ij gλ_i + F_ij G_ij,   F_ij = (λ_j − λ_i) / ((λ_j − λ_i)² + ε²),
//   ε = gap_eps·max_k|λ_k| + eps_floor,   gC = V · (M + Mᵀ)/2 · Vᵀ.
// F_ij → 1/(λ_j − λ_i) for separated eigenvalues (the exact derivative dv_j = Σ_i v_i v_iᵀ dC v_j /
// (λ_j − λ_i)) and → 0 for equal ones; the denominator is >= eps_floor² > 0. The formula holds for any
// fixed sign of each column, so the det fix of step 6 does not change it.
#include <cmath>
#include <cstdint>
#include <omp.h>
#include <utility>

namespace {

// p/max|S_ij| at or below this is isotropic: the anisotropic part is at the rounding level of S.
constexpr double ISOTROPIC_REL = 1e-14;
// Batches smaller than this run on the calling thread (a parallel region costs more than they do).
constexpr int64_t MIN_PARALLEL_N = 4096;

struct Sym3 {
    double xx, yy, zz, xy, xz, yz;
};

inline double dot3(const double* a, const double* b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

inline void cross3(const double* a, const double* b, double* out) {
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

inline void scale3(double* v, double f) {
    v[0] *= f;
    v[1] *= f;
    v[2] *= f;
}

inline double quadratic_form(const Sym3& a, const double* u, const double* w) {  // uᵀ A w
    return u[0] * (a.xx * w[0] + a.xy * w[1] + a.xz * w[2]) + u[1] * (a.xy * w[0] + a.yy * w[1] + a.yz * w[2]) +
           u[2] * (a.xz * w[0] + a.yz * w[1] + a.zz * w[2]);
}

inline double max_abs_entry(const Sym3& s) {
    const double m1 = std::fmax(std::fabs(s.xx), std::fmax(std::fabs(s.yy), std::fabs(s.zz)));
    const double m2 = std::fmax(std::fabs(s.xy), std::fmax(std::fabs(s.xz), std::fabs(s.yz)));
    return std::fmax(m1, m2);
}

inline double determinant(const Sym3& a) {
    return a.xx * (a.yy * a.zz - a.yz * a.yz) - a.xy * (a.xy * a.zz - a.yz * a.xz) + a.xz * (a.xy * a.yz - a.yy * a.xz);
}

// The isolated eigenvalue of B (tr B = 0, ‖B‖²_F = 6) by the trigonometric method: θ1 = 2cos φ and
// θ3 = 2cos(φ + 2π/3) with φ = acos(r)/3, r = det(B)/2. θ1 − θ2 >= θ2 − θ3 ⟺ θ2 <= 0 ⟺ r >= 0, and
// B → −B maps θ3 to −θ1, so θ_iso = sign(r)·2cos(acos(|r|)/3) (one acos, one cos).
inline double isolated_eigenvalue(const Sym3& b) {
    const double r = std::fmin(1.0, std::fmax(-1.0, 0.5 * determinant(b)));
    const double theta = 2.0 * std::cos(std::acos(std::fabs(r)) / 3.0);
    return r >= 0.0 ? theta : -theta;
}

// Unit null vector of (A − λI) for an isolated eigenvalue λ: the largest-norm cross product of two rows
// (Kopp). False if every cross product vanishes (not an isolated eigenvalue).
inline bool isolated_eigenvector(const Sym3& a, double lam, double* v) {
    const double r0[3] = {a.xx - lam, a.xy, a.xz};
    const double r1[3] = {a.xy, a.yy - lam, a.yz};
    const double r2[3] = {a.xz, a.yz, a.zz - lam};
    double c[3][3];
    cross3(r0, r1, c[0]);
    cross3(r0, r2, c[1]);
    cross3(r1, r2, c[2]);
    int best = 0;
    double best_norm2 = dot3(c[0], c[0]);
    for (int k = 1; k < 3; ++k) {
        const double n2 = dot3(c[k], c[k]);
        if (n2 > best_norm2) {
            best_norm2 = n2;
            best = k;
        }
    }
    if (!(best_norm2 > 0.0)) return false;
    const double inv = 1.0 / std::sqrt(best_norm2);
    for (int i = 0; i < 3; ++i) v[i] = c[best][i] * inv;
    return true;
}

// Orthonormal u, w with (v, u, w) right-handed, for a unit v: u ∝ v × e_k with e_k the axis least aligned
// with v (|v × e_k|² = 1 − v_k² >= 2/3).
inline void orthonormal_complement(const double* v, double* u, double* w) {
    const double ax = std::fabs(v[0]), ay = std::fabs(v[1]), az = std::fabs(v[2]);
    const int k = (ax <= ay && ax <= az) ? 0 : (ay <= az ? 1 : 2);
    const double e[3] = {k == 0 ? 1.0 : 0.0, k == 1 ? 1.0 : 0.0, k == 2 ? 1.0 : 0.0};
    cross3(v, e, u);
    scale3(u, 1.0 / std::sqrt(dot3(u, u)));
    cross3(v, u, w);
}

struct Eigen3 {
    double lam[3];     // eigenvalues of A
    double vec[3][3];  // vec[k] = unit eigenvector of lam[k]
};

// The two eigenpairs of A restricted to span(u, w), larger first: B = [u w]ᵀ A [u w] has eigenvalues
// m ± ρ, m = (B11 + B22)/2, h = (B11 − B22)/2, ρ = sqrt(h² + B12²), and every column of
// B − (m − ρ)I = [[h + ρ, B12], [B12, ρ − h]] is ∝ the larger one's eigenvector; the column without
// cancellation (the first if h >= 0) is used. ρ = 0: B = mI, (u, w) is already an eigenbasis.
inline void solve_pair(const Sym3& a, const double* u, const double* w, double* lam, double (*vec)[3]) {
    const double b11 = quadratic_form(a, u, u), b22 = quadratic_form(a, w, w), b12 = quadratic_form(a, u, w);
    const double mean = 0.5 * (b11 + b22), half_diff = 0.5 * (b11 - b22);
    const double radius = std::sqrt(half_diff * half_diff + b12 * b12);
    double x = half_diff >= 0.0 ? half_diff + radius : b12;
    double y = half_diff >= 0.0 ? b12 : radius - half_diff;
    const double norm2 = x * x + y * y;
    if (norm2 > 0.0) {
        const double inv = 1.0 / std::sqrt(norm2);
        x *= inv;
        y *= inv;
    } else {
        x = 1.0;
        y = 0.0;
    }
    lam[0] = mean + radius;
    lam[1] = mean - radius;
    for (int i = 0; i < 3; ++i) {
        vec[0][i] = x * u[i] + y * w[i];
        vec[1][i] = -y * u[i] + x * w[i];
    }
}

inline void swap_pairs(Eigen3& e, int i, int j) {
    std::swap(e.lam[i], e.lam[j]);
    for (int k = 0; k < 3; ++k) std::swap(e.vec[i][k], e.vec[j][k]);
}

inline void sort_descending(Eigen3& e) {
    if (e.lam[0] < e.lam[1]) swap_pairs(e, 0, 1);
    if (e.lam[1] < e.lam[2]) swap_pairs(e, 1, 2);
    if (e.lam[0] < e.lam[1]) swap_pairs(e, 0, 1);
}

// Steps 3–6 of the header for A = S/s − qI with p > 0. False: no isolated eigenvalue found.
inline bool decompose_shifted(const Sym3& a, double p, Eigen3& e) {
    const double inv_p = 1.0 / p;
    const Sym3 b = {a.xx * inv_p, a.yy * inv_p, a.zz * inv_p, a.xy * inv_p, a.xz * inv_p, a.yz * inv_p};
    const double theta = isolated_eigenvalue(b);
    const int iso = theta >= 0.0 ? 0 : 2;
    double v[3], u[3], w[3];
    if (!isolated_eigenvector(a, p * theta, v)) return false;
    orthonormal_complement(v, u, w);
    const int first_pair = iso == 0 ? 1 : 0;
    solve_pair(a, u, w, e.lam + first_pair, e.vec + first_pair);
    e.lam[iso] = quadratic_form(a, v, v);
    for (int i = 0; i < 3; ++i) e.vec[iso][i] = v[i];
    sort_descending(e);
    cross3(e.vec[0], e.vec[1], e.vec[2]);
    return true;
}

inline void write_isotropic(double lam_value, double* lam, double* V) {
    for (int k = 0; k < 3; ++k) lam[k] = lam_value;
    for (int i = 0; i < 9; ++i) V[i] = (i % 4 == 0) ? 1.0 : 0.0;
}

void decompose(const double* c, double* lam, double* V) {
    const Sym3 sym = {c[0], c[4], c[8], 0.5 * (c[1] + c[3]), 0.5 * (c[2] + c[6]), 0.5 * (c[5] + c[7])};
    const double s = max_abs_entry(sym);
    if (!(s > 0.0)) {
        write_isotropic(0.0, lam, V);
        return;
    }
    const double inv_s = 1.0 / s;
    const double q = (sym.xx + sym.yy + sym.zz) * inv_s / 3.0;
    const Sym3 a = {sym.xx * inv_s - q, sym.yy * inv_s - q, sym.zz * inv_s - q,
                    sym.xy * inv_s, sym.xz * inv_s, sym.yz * inv_s};
    const double p = std::sqrt((a.xx * a.xx + a.yy * a.yy + a.zz * a.zz +
                                2.0 * (a.xy * a.xy + a.xz * a.xz + a.yz * a.yz)) / 6.0);
    Eigen3 e;
    if (!(p > ISOTROPIC_REL) || !decompose_shifted(a, p, e)) {
        write_isotropic((sym.xx + sym.yy + sym.zz) / 3.0, lam, V);
        return;
    }
    for (int k = 0; k < 3; ++k) {
        lam[k] = s * (e.lam[k] + q);
        for (int i = 0; i < 3; ++i) V[3 * i + k] = e.vec[k][i];
    }
}

// gC for one matrix (see the header): V row-major with eigenvector columns.
void backward_one(const double* lam, const double* V, const double* g_lam, const double* g_V, double gap_eps,
                  double eps_floor, double* g_C) {
    const double lam_abs = std::fmax(std::fabs(lam[0]), std::fmax(std::fabs(lam[1]), std::fabs(lam[2])));
    const double eps = gap_eps * lam_abs + eps_floor;
    const double eps2 = eps * eps;
    double M[3][3];
    for (int i = 0; i < 3; ++i) {
        for (int j = 0; j < 3; ++j) {
            if (i == j) {
                M[i][j] = g_lam[i];
                continue;
            }
            double G = 0.0;  // (Vᵀ gV)_ij
            for (int r = 0; r < 3; ++r) G += V[3 * r + i] * g_V[3 * r + j];
            const double d = lam[j] - lam[i];
            M[i][j] = d / (d * d + eps2) * G;
        }
    }
    double Ms[3][3], VM[3][3];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) Ms[i][j] = 0.5 * (M[i][j] + M[j][i]);
    for (int r = 0; r < 3; ++r)
        for (int j = 0; j < 3; ++j) VM[r][j] = V[3 * r] * Ms[0][j] + V[3 * r + 1] * Ms[1][j] + V[3 * r + 2] * Ms[2][j];
    for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
            g_C[3 * r + c] = VM[r][0] * V[3 * c] + VM[r][1] * V[3 * c + 1] + VM[r][2] * V[3 * c + 2];
}

}  // namespace

extern "C" {

// C (n, 3, 3) → lam (n, 3) descending, V (n, 3, 3) eigenvector columns; float64, C-contiguous.
int gs_sym3_eigh_forward(int64_t n, const double* C, double* lam, double* V, int64_t nthreads) {
    if (n < 0 || nthreads < 1) return -1;
#pragma omp parallel for num_threads((int)nthreads) schedule(static) if (n >= MIN_PARALLEL_N)
    for (int64_t k = 0; k < n; ++k) decompose(C + 9 * k, lam + 3 * k, V + 9 * k);
    return 0;
}

// (lam, V) from the forward and the upstream g_lam (n, 3), g_V (n, 3, 3) → g_C (n, 3, 3) (symmetric).
int gs_sym3_eigh_backward(int64_t n, const double* lam, const double* V, const double* g_lam, const double* g_V,
                          double gap_eps, double eps_floor, double* g_C, int64_t nthreads) {
    if (n < 0 || nthreads < 1 || !(eps_floor > 0.0) || !(gap_eps >= 0.0)) return -1;
#pragma omp parallel for num_threads((int)nthreads) schedule(static) if (n >= MIN_PARALLEL_N)
    for (int64_t k = 0; k < n; ++k)
        backward_one(lam + 3 * k, V + 9 * k, g_lam + 3 * k, g_V + 9 * k, gap_eps, eps_floor, g_C + 9 * k);
    return 0;
}

}  // extern "C"
