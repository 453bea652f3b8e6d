// IBGS's per-step frame bookkeeping without autograd: the column permutation and signs that keep each
// Gaussian's eigenvector frame continuous (gsbench/geometry/local_geometry.py, `frame_alignment`), and
// rotation matrix -> unit quaternion (gsbench/geometry/rotations.py, `rotmat_to_quat`) for inputs that need
// no gradient. The PyTorch functions are the references; tests: tests/test_frames_fused.py.
//
// Layout: V, previous, R (N, 3, 3) row-major, columns are the frame's axes; perm (N, 3) int64; signs (N, 3)
// and q (N, 4) (w, x, y, z) float64. V and R are float64; previous float32 or float64.
//
// Alignment, per Gaussian: dots[k][m] = previous column k · V column m; over the candidate permutations p
// (all six; for surfels the two that keep column 2) the score Σ_k |dots[k][p(k)]|, the first maximum wins;
// signs[k] = −1 where dots[k][p(k)] < 0, else 1; if the aligned frame V[:, p]·signs has det < 0, the sign of
// the least aligned column (smallest |dots[k][p(k)]|, column 2 excluded for surfels) is flipped.
//
// Quaternion (Shepperd): of the radicands 1 + tr, 1 + 2R00 − tr, 1 + 2R11 − tr, 1 + 2R22 − tr the first
// largest is used, s = 2 sqrt(max(radicand, 1e−12)) (= 4·|that component|), the other components from the
// differences / sums of the off-diagonal pairs divided by s; the result is negated if w < 0 and normalised
// by max(|q|, 1e−12).
#include <cmath>
#include <cstdint>
#include <omp.h>

namespace {

constexpr int64_t MIN_PARALLEL = 4096;
constexpr int PERMS_3D[6][3] = {{0, 1, 2}, {0, 2, 1}, {1, 0, 2}, {1, 2, 0}, {2, 0, 1}, {2, 1, 0}};
constexpr int PERMS_2D[2][3] = {{0, 1, 2}, {1, 0, 2}};

inline double det3(const double m[9]) {
    return m[0] * (m[4] * m[8] - m[5] * m[7]) - m[1] * (m[3] * m[8] - m[5] * m[6]) + m[2] * (m[3] * m[7] - m[4] * m[6]);
}

template <typename P>
void align(int64_t N, bool surfel, const double* V, const P* previous, int64_t* perm, double* signs, int64_t nthreads) {
    const int count = surfel ? 2 : 6;
#pragma omp parallel for schedule(static) num_threads(nthreads < 1 ? 1 : (int)nthreads) if (N >= MIN_PARALLEL)
    for (int64_t i = 0; i < N; ++i) {
        const double* v = V + 9 * i;
        const P* prev = previous + 9 * i;
        double dots[3][3];
        for (int k = 0; k < 3; ++k)
            for (int m = 0; m < 3; ++m)
                dots[k][m] = static_cast<double>(prev[k]) * v[m] + static_cast<double>(prev[3 + k]) * v[3 + m] +
                             static_cast<double>(prev[6 + k]) * v[6 + m];
        int best = 0;
        double best_score = -1.0;
        for (int c = 0; c < count; ++c) {
            const int* p = surfel ? PERMS_2D[c] : PERMS_3D[c];
            const double score = std::fabs(dots[0][p[0]]) + std::fabs(dots[1][p[1]]) + std::fabs(dots[2][p[2]]);
            if (score > best_score) {
                best_score = score;
                best = c;
            }
        }
        const int* p = surfel ? PERMS_2D[best] : PERMS_3D[best];
        double s[3], aligned[3], frame[9];
        for (int k = 0; k < 3; ++k) {
            aligned[k] = dots[k][p[k]];
            s[k] = aligned[k] < 0 ? -1.0 : 1.0;
            for (int row = 0; row < 3; ++row) frame[3 * row + k] = v[3 * row + p[k]] * s[k];
        }
        if (det3(frame) < 0) {
            int weakest = 0;
            double weakest_value = 0.0;
            for (int k = 0; k < 3; ++k) {
                const double value = std::fabs(aligned[k]) + (surfel && k == 2 ? 1.0 : 0.0);
                if (k == 0 || value < weakest_value) {
                    weakest_value = value;
                    weakest = k;
                }
            }
            s[weakest] = -s[weakest];
        }
        for (int k = 0; k < 3; ++k) {
            perm[3 * i + k] = p[k];
            signs[3 * i + k] = s[k];
        }
    }
}

// The three off-diagonal combinations of each Shepperd branch: {index into a = (d21, d02, d10, s01, s02, s12),
// quaternion component}; and the signs of (m00, m11, m22) in each branch's radicand.
constexpr int PAIRS[4][3][2] = {{{0, 1}, {1, 2}, {2, 3}}, {{0, 0}, {3, 2}, {4, 3}},
                                {{1, 0}, {3, 1}, {5, 3}}, {{2, 0}, {4, 1}, {5, 2}}};
constexpr double DIAG[4][3] = {{1, 1, 1}, {1, -1, -1}, {-1, 1, -1}, {-1, -1, 1}};

// Shepperd's unnormalised quaternion of m (header): branch c (the first largest radicand), s = 2√max(r_c, 1e-12),
// a = (m21 − m12, m02 − m20, m10 − m01, m01 + m10, m02 + m20, m12 + m21), q̃ (q̃_c = s/4, the other three a_k/s),
// the sign that makes w >= 0 and |q̃|.
struct Shepperd {
    int c;
    bool inside;  // r_c > 1e-12 (s depends on m)
    double s, a[6], qt[4], sign, norm;
};

inline Shepperd shepperd(const double* m) {
    Shepperd h;
    const double tr = m[0] + m[4] + m[8];
    const double rad[4] = {1 + tr, 1 + 2 * m[0] - tr, 1 + 2 * m[4] - tr, 1 + 2 * m[8] - tr};
    h.c = 0;
    for (int j = 1; j < 4; ++j)
        if (rad[j] > rad[h.c]) h.c = j;
    h.inside = rad[h.c] > 1e-12;
    h.s = 2 * std::sqrt(h.inside ? rad[h.c] : 1e-12);
    const double a[6] = {m[7] - m[5], m[2] - m[6], m[3] - m[1], m[1] + m[3], m[2] + m[6], m[5] + m[7]};
    for (int k = 0; k < 6; ++k) h.a[k] = a[k];
    h.qt[h.c] = h.s / 4;
    for (const auto& pk : PAIRS[h.c]) h.qt[pk[1]] = a[pk[0]] / h.s;
    h.sign = h.qt[0] < 0 ? -1.0 : 1.0;
    h.norm = std::sqrt(h.qt[0] * h.qt[0] + h.qt[1] * h.qt[1] + h.qt[2] * h.qt[2] + h.qt[3] * h.qt[3]);
    return h;
}

void to_quaternion(int64_t N, const double* R, double* q, int64_t nthreads) {
#pragma omp parallel for schedule(static) num_threads(nthreads < 1 ? 1 : (int)nthreads) if (N >= MIN_PARALLEL)
    for (int64_t i = 0; i < N; ++i) {
        const Shepperd h = shepperd(R + 9 * i);
        const double den = h.norm > 1e-12 ? h.norm : 1e-12;
        for (int j = 0; j < 4; ++j) q[4 * i + j] = h.sign * h.qt[j] / den;
    }
}

// dL/dR (N, 3, 3) from dL/dq (N, 4) through `to_quaternion`, the branch and the sign held (piecewise derivative,
// as autograd through the reference): q = σ q̃/|q̃| gives dq̃ = σ (g − q (q·g))/|q̃|; q̃_c = s/4 and the other three
// components a_k/s give ds = dq̃_c/4 − Σ dq̃_k a_k/s² and da_k = dq̃_k/s; s = 2√r (r the branch's radicand, above
// 1e-12) gives dr = 2 ds/s, spread on the diagonal with the radicand's signs.
void to_quaternion_backward(int64_t N, const double* R, const double* gq, double* gR, int64_t nthreads) {
#pragma omp parallel for schedule(static) num_threads(nthreads < 1 ? 1 : (int)nthreads) if (N >= MIN_PARALLEL)
    for (int64_t i = 0; i < N; ++i) {
        const Shepperd h = shepperd(R + 9 * i);
        const int c = h.c;
        const double den = h.norm > 1e-12 ? h.norm : 1e-12;
        const double* g = gq + 4 * i;
        double q[4], qg = 0;
        for (int j = 0; j < 4; ++j) {
            q[j] = h.sign * h.qt[j] / den;
            qg += q[j] * g[j];
        }
        double dqt[4];
        for (int j = 0; j < 4; ++j) dqt[j] = h.norm > 1e-12 ? h.sign * (g[j] - q[j] * qg) / den : h.sign * g[j] / den;
        double ds = dqt[c] / 4, da[6] = {0, 0, 0, 0, 0, 0};
        for (const auto& pk : PAIRS[c]) {
            ds -= dqt[pk[1]] * h.a[pk[0]] / (h.s * h.s);
            da[pk[0]] = dqt[pk[1]] / h.s;
        }
        const double dr = h.inside ? 2 * ds / h.s : 0.0;
        double* o = gR + 9 * i;
        o[0] = dr * DIAG[c][0];
        o[4] = dr * DIAG[c][1];
        o[8] = dr * DIAG[c][2];
        o[7] = da[0] + da[5];  // d21 = m21 − m12, s12 = m12 + m21
        o[5] = -da[0] + da[5];
        o[2] = da[1] + da[4];  // d02 = m02 − m20, s02 = m02 + m20
        o[6] = -da[1] + da[4];
        o[3] = da[2] + da[3];  // d10 = m10 − m01, s01 = m01 + m10
        o[1] = -da[2] + da[3];
    }
}

}  // namespace

extern "C" {

// perm (N, 3) and signs (N, 3) aligning V to previous (header); previous_dtype 0: float32, 1: float64.
int gs_frame_alignment(int64_t N, int64_t surfel, const double* V, const void* previous, int64_t previous_dtype,
                       int64_t* perm, double* signs, int64_t nthreads) {
    if (N < 0) return 1;
    if (previous_dtype == 1) align(N, surfel != 0, V, static_cast<const double*>(previous), perm, signs, nthreads);
    else align(N, surfel != 0, V, static_cast<const float*>(previous), perm, signs, nthreads);
    return 0;
}

// q (N, 4) unit quaternions, w >= 0, of the rotations R (N, 3, 3) (header).
int gs_rotmat_to_quat(int64_t N, const double* R, double* q, int64_t nthreads) {
    if (N < 0) return 1;
    to_quaternion(N, R, q, nthreads);
    return 0;
}

// gR (N, 3, 3) = dL/dR of `gs_rotmat_to_quat` given gq = dL/dq (N, 4) (to_quaternion_backward).
int gs_rotmat_to_quat_backward(int64_t N, const double* R, const double* gq, double* gR, int64_t nthreads) {
    if (N < 0) return 1;
    to_quaternion_backward(N, R, gq, gR, nthreads);
    return 0;
}

}  // extern "C"
