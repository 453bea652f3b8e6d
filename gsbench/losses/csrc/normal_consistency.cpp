// Fused depth-normal consistency term (the `normal_consistency` loss of 2DGS, GOF, RaDe-GS and IBGS) and
// its backward, float32 and float64 maps. Python API and the PyTorch reference: gsbench/losses/normal_consistency.py;
// tests: tests/test_normal_consistency_fused.py. Plain C ABI, OpenMP over image rows.
//
// Layout: normal (H, W, 3), depth maps d1, d2 and alpha (H, W), all C-contiguous and of one dtype; d2 and
// alpha may be NULL. Intrinsics fx, fy, cx, cy in pixels (pixel centres at i + 0.5).
//
// Forward. The camera-space point of pixel (r, c) is X(r, c) = D(r, c) · ((c + 0.5 − cx)/fx, (r + 0.5 − cy)/fy, 1).
// At an interior pixel (1 <= r <= H−2, 1 <= c <= W−2) of depth map D:
//   dx = X(r+1, c) − X(r−1, c),   dy = X(r, c+1) − X(r, c−1),   k = dx × dy,   N(D) = k / max(|k|, ε),
// and N(D) = 0 on the one-pixel border (ε = 1e-12, torch.nn.functional.normalize's). Then per pixel
//   n_d = (w1 N(d1) + w2 N(d2)) · a,   a = alpha (when given; it carries no gradient) or 1,
//   n_r = n / max(|n|, ε) when normalize, else n,
//   s = 1 − n_r · n_d,
// and the forward returns Σ_pixels s in float64 (the caller divides by H·W for the mean). All arithmetic
// is float64 whatever the storage type.
//
// Backward, for G = dL/dΣs (so dL/ds = G at every pixel):
//   dL/dn_r = −G n_d;  dL/dn = (dL/dn_r − n_r (n_r · dL/dn_r)) / |n| when normalize and |n| > ε,
//                      dL/dn_r / ε when normalize and |n| <= ε (the clamp passes no gradient to |n|),
//                      dL/dn_r otherwise;
//   dL/dN_j = −G w_j a n_r;  dL/dk = (dL/dN_j − N_j (N_j · dL/dN_j)) / |k| (or dL/dN_j / ε, as above);
//   dL/d(dx) = dy × dL/dk,   dL/d(dy) = dL/dk × dx          (since g · (dx × dy) = dx · (dy × g) = dy · (g × dx));
// each interior pixel p adds ±dL/d(dx) to X at p ± one row and ±dL/d(dy) to X at p ± one column, and
//   dL/dD(q) = ray(q) · dL/dX(q).
// The scatter is done as a gather: pass 1 stores (dL/d(dx), dL/d(dy)) per interior pixel (6 doubles, 0 on
// the border), pass 2 sums, for each pixel q, +dL/d(dx) of the pixel above, −that of the pixel below,
// +dL/d(dy) of the pixel to the left and −that of the pixel to the right.
#include <cmath>
#include <cstdint>
#include <omp.h>
#include <vector>

namespace {

constexpr double EPS = 1e-12;
// Maps with fewer pixels than this run on the calling thread (a parallel region costs more than they do).
constexpr int64_t MIN_PARALLEL = 8192;

struct View {
    int64_t H, W;
    std::vector<double> rx, ry;  // ray components (c + 0.5 − cx)/fx per column, (r + 0.5 − cy)/fy per row
    View(int64_t H_, int64_t W_, double fx, double fy, double cx, double cy) : H(H_), W(W_), rx(W_), ry(H_) {
        for (int64_t c = 0; c < W; ++c) rx[c] = (c + 0.5 - cx) / fx;
        for (int64_t r = 0; r < H; ++r) ry[r] = (r + 0.5 - cy) / fy;
    }
    bool interior(int64_t r, int64_t c) const { return r >= 1 && r <= H - 2 && c >= 1 && c <= W - 2; }
    void ray(int64_t r, int64_t c, double out[3]) const {
        out[0] = rx[c];
        out[1] = ry[r];
        out[2] = 1.0;
    }
};

inline double dot3(const double a[3], const double b[3]) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }

inline void cross3(const double a[3], const double b[3], double out[3]) {
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

template <typename T>
inline void point(const T* D, const View& v, int64_t r, int64_t c, double out[3]) {
    double ray[3];
    v.ray(r, c, ray);
    const double d = static_cast<double>(D[r * v.W + c]);
    for (int i = 0; i < 3; ++i) out[i] = d * ray[i];
}

// dx, dy, k = dx × dy and |k| at the interior pixel (r, c) of D.
template <typename T>
inline double depth_cross(const T* D, const View& v, int64_t r, int64_t c, double dx[3], double dy[3], double k[3]) {
    double a[3], b[3];
    point(D, v, r + 1, c, a);
    point(D, v, r - 1, c, b);
    for (int i = 0; i < 3; ++i) dx[i] = a[i] - b[i];
    point(D, v, r, c + 1, a);
    point(D, v, r, c - 1, b);
    for (int i = 0; i < 3; ++i) dy[i] = a[i] - b[i];
    cross3(dx, dy, k);
    return std::sqrt(dot3(k, k));
}

// g through x / max(|x|, ε) at x = unit·len: (g − unit (unit · g)) / len, or g / ε when len <= ε.
inline void normalize_backward(const double unit[3], double len, const double g[3], double out[3]) {
    if (len > EPS) {
        const double u = dot3(unit, g);
        for (int i = 0; i < 3; ++i) out[i] = (g[i] - unit[i] * u) / len;
    } else {
        for (int i = 0; i < 3; ++i) out[i] = g[i] / EPS;
    }
}

// n_r (and |n|) of pixel p.
template <typename T>
inline double rendered_normal(const T* n, int64_t p, bool normalize, double nr[3]) {
    for (int i = 0; i < 3; ++i) nr[i] = static_cast<double>(n[3 * p + i]);
    const double len = std::sqrt(dot3(nr, nr));
    if (normalize) {
        const double den = len > EPS ? len : EPS;
        for (int i = 0; i < 3; ++i) nr[i] /= den;
    }
    return len;
}

// n_d of pixel (r, c) without the alpha factor: w1 N(d1) + w2 N(d2) (d2 may be NULL), 0 on the border.
template <typename T>
inline void depth_normal(const T* d1, const T* d2, double w1, double w2, const View& v, int64_t r, int64_t c,
                         double nd[3]) {
    nd[0] = nd[1] = nd[2] = 0.0;
    if (!v.interior(r, c)) return;
    const T* maps[2] = {d1, d2};
    const double weights[2] = {w1, w2};
    for (int j = 0; j < 2; ++j) {
        if (maps[j] == nullptr) continue;
        double dx[3], dy[3], k[3];
        const double len = depth_cross(maps[j], v, r, c, dx, dy, k);
        const double den = len > EPS ? len : EPS;
        for (int i = 0; i < 3; ++i) nd[i] += weights[j] * k[i] / den;
    }
}

template <typename T>
double forward(const View& v, const T* n, const T* d1, const T* d2, const T* alpha, double w1, double w2,
               bool normalize, int64_t nthreads) {
    double total = 0.0;
#pragma omp parallel for schedule(static) reduction(+ : total) num_threads(nthreads < 1 ? 1 : (int)nthreads) if (v.H * v.W >= MIN_PARALLEL)
    for (int64_t r = 0; r < v.H; ++r) {
        double row = 0.0;
        for (int64_t c = 0; c < v.W; ++c) {
            const int64_t p = r * v.W + c;
            double nr[3], nd[3];
            rendered_normal(n, p, normalize, nr);
            depth_normal(d1, d2, w1, w2, v, r, c, nd);
            const double a = alpha ? static_cast<double>(alpha[p]) : 1.0;
            row += 1.0 - a * dot3(nr, nd);
        }
        total += row;
    }
    return total;
}

// Pass 1: dL/dn of every pixel into gn (when not NULL) and, for each map j with a gradient wanted,
// (dL/d(dx), dL/d(dy)) of every interior pixel into buf[j] (H·W·6, 0 on the border); one evaluation of
// n_r and of each map's cross product per pixel serves both.
template <typename T>
void pixel_gradients(const View& v, const T* n, const T* const maps[2], const double weights[2], const bool want[2],
                     const T* alpha, bool normalize, double G, T* gn, double* const buf[2], int64_t nthreads) {
#pragma omp parallel for schedule(static) num_threads(nthreads < 1 ? 1 : (int)nthreads) if (v.H * v.W >= MIN_PARALLEL)
    for (int64_t r = 0; r < v.H; ++r) {
        for (int64_t c = 0; c < v.W; ++c) {
            const int64_t p = r * v.W + c;
            const bool inner = v.interior(r, c);
            double nr[3], nd[3] = {0.0, 0.0, 0.0}, dx[2][3], dy[2][3], unit[2][3], len[2] = {0.0, 0.0};
            const double n_len = rendered_normal(n, p, normalize, nr);
            const double a = alpha ? static_cast<double>(alpha[p]) : 1.0;
            for (int j = 0; j < 2 && inner; ++j) {
                if (maps[j] == nullptr) continue;
                double k[3];
                len[j] = depth_cross(maps[j], v, r, c, dx[j], dy[j], k);
                const double den = len[j] > EPS ? len[j] : EPS;
                for (int i = 0; i < 3; ++i) {
                    unit[j][i] = k[i] / den;
                    nd[i] += weights[j] * unit[j][i];
                }
            }
            if (gn) {
                double g[3], out[3];
                for (int i = 0; i < 3; ++i) g[i] = -G * a * nd[i];
                if (normalize) normalize_backward(nr, n_len, g, out);
                else for (int i = 0; i < 3; ++i) out[i] = g[i];
                for (int i = 0; i < 3; ++i) gn[3 * p + i] = static_cast<T>(out[i]);
            }
            for (int j = 0; j < 2; ++j) {
                if (!want[j]) continue;
                double* out = buf[j] + 6 * p;
                if (!inner) {
                    for (int i = 0; i < 6; ++i) out[i] = 0.0;
                    continue;
                }
                double gN[3], gk[3];
                for (int i = 0; i < 3; ++i) gN[i] = -G * weights[j] * a * nr[i];
                normalize_backward(unit[j], len[j], gN, gk);
                cross3(dy[j], gk, out);
                cross3(gk, dx[j], out + 3);
            }
        }
    }
}

// Pass 2: dL/dD(q) = ray(q) · (+g_dx above − g_dx below + g_dy left − g_dy right).
template <typename T>
void gather_depth_gradient(const View& v, const double* buf, T* gD, int64_t nthreads) {
#pragma omp parallel for schedule(static) num_threads(nthreads < 1 ? 1 : (int)nthreads) if (v.H * v.W >= MIN_PARALLEL)
    for (int64_t r = 0; r < v.H; ++r) {
        for (int64_t c = 0; c < v.W; ++c) {
            double gX[3] = {0.0, 0.0, 0.0};
            if (r >= 1) for (int i = 0; i < 3; ++i) gX[i] += buf[6 * ((r - 1) * v.W + c) + i];
            if (r + 1 < v.H) for (int i = 0; i < 3; ++i) gX[i] -= buf[6 * ((r + 1) * v.W + c) + i];
            if (c >= 1) for (int i = 0; i < 3; ++i) gX[i] += buf[6 * (r * v.W + c - 1) + 3 + i];
            if (c + 1 < v.W) for (int i = 0; i < 3; ++i) gX[i] -= buf[6 * (r * v.W + c + 1) + 3 + i];
            double ray[3];
            v.ray(r, c, ray);
            gD[r * v.W + c] = static_cast<T>(dot3(ray, gX));
        }
    }
}

template <typename T>
void backward(const View& v, const T* n, const T* d1, const T* d2, const T* alpha, double w1, double w2,
              bool normalize, double G, T* gn, T* gd1, T* gd2, int64_t nthreads) {
    const T* maps[2] = {d1, d2};
    T* grads[2] = {gd1, gd2};
    const double weights[2] = {w1, w2};
    const bool want[2] = {d1 != nullptr && gd1 != nullptr, d2 != nullptr && gd2 != nullptr};
    // kept between calls: fresh 1–2 MB buffers cost their page faults on every step
    thread_local std::vector<double> storage;
    const size_t size = static_cast<size_t>(v.H * v.W * 6);
    if (storage.size() < 2 * size) storage.resize(2 * size);
    double* const buf[2] = {storage.data(), storage.data() + size};
    pixel_gradients(v, n, maps, weights, want, alpha, normalize, G, gn, buf, nthreads);
    for (int j = 0; j < 2; ++j)
        if (want[j]) gather_depth_gradient(v, buf[j], grads[j], nthreads);
}

}  // namespace

extern "C" {

// Σ over pixels of 1 − n_r · n_d (header) into *out_sum. dtype 0: float32, 1: float64. Returns 0, or 1 on bad sizes.
int gs_normal_consistency_forward(int64_t H, int64_t W, int64_t dtype, const void* normal, const void* d1,
                                  const void* d2, const void* alpha, double w1, double w2, int64_t normalize,
                                  double fx, double fy, double cx, double cy, double* out_sum, int64_t nthreads) {
    if (H < 1 || W < 1 || normal == nullptr || d1 == nullptr || out_sum == nullptr) return 1;
    const View v(H, W, fx, fy, cx, cy);
    if (dtype == 1)
        *out_sum = forward(v, static_cast<const double*>(normal), static_cast<const double*>(d1),
                           static_cast<const double*>(d2), static_cast<const double*>(alpha), w1, w2, normalize != 0,
                           nthreads);
    else
        *out_sum = forward(v, static_cast<const float*>(normal), static_cast<const float*>(d1),
                           static_cast<const float*>(d2), static_cast<const float*>(alpha), w1, w2, normalize != 0,
                           nthreads);
    return 0;
}

// Gradients of G · Σ s (header) into g_normal (H, W, 3), g_d1, g_d2 (H, W); any of them may be NULL.
int gs_normal_consistency_backward(int64_t H, int64_t W, int64_t dtype, const void* normal, const void* d1,
                                   const void* d2, const void* alpha, double w1, double w2, int64_t normalize,
                                   double fx, double fy, double cx, double cy, double G, void* g_normal, void* g_d1,
                                   void* g_d2, int64_t nthreads) {
    if (H < 1 || W < 1 || normal == nullptr || d1 == nullptr) return 1;
    const View v(H, W, fx, fy, cx, cy);
    if (dtype == 1)
        backward(v, static_cast<const double*>(normal), static_cast<const double*>(d1), static_cast<const double*>(d2),
                 static_cast<const double*>(alpha), w1, w2, normalize != 0, G, static_cast<double*>(g_normal),
                 static_cast<double*>(g_d1), static_cast<double*>(g_d2), nthreads);
    else
        backward(v, static_cast<const float*>(normal), static_cast<const float*>(d1), static_cast<const float*>(d2),
                 static_cast<const float*>(alpha), w1, w2, normalize != 0, G, static_cast<float*>(g_normal),
                 static_cast<float*>(g_d1), static_cast<float*>(g_d2), nthreads);
    return 0;
}

}  // extern "C"
