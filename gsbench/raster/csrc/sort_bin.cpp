// gsbench tile rasterizer: the visible Gaussians sorted by depth (LSD radix sort) and their per-tile lists by
// bounding rectangle (a counting sort that keeps every tile list front to back).

#include "raster_common.h"

namespace {

// Counting sort of M depth-ordered entries into per-tile lists, shared by gs_bin and gs_bin_sorted:
// per-thread tile counts, a prefix sum into ``offsets`` (ntiles + 1), then each thread fills the tiles
// of its own band of tile rows (bands hold about equal pair counts), reading the entries in depth
// order so every tile list stays front to back. ``rect_of(j)`` gives entry j's x0 x1 y0 y1 (exclusive
// ends), ``id_of(j)`` its Gaussian id. Returns the pair count, or -1 if it exceeds ``capacity``.
template <class RectOf, class IdOf>
int64_t bin_entries(int64_t M, RectOf rect_of, IdOf id_of, int64_t tiles_x, int64_t tiles_y, int32_t* offsets,
                    int32_t* list, int64_t capacity, int64_t nthreads) {
    const int64_t ntiles = tiles_x * tiles_y;
    const int nt = (int)std::max<int64_t>(1, nthreads);
    std::vector<std::vector<int32_t>> counts(nt, std::vector<int32_t>(ntiles, 0));
#pragma omp parallel num_threads(nt)
    {
        auto& c = counts[omp_get_thread_num()];
#pragma omp for schedule(static)
        for (int64_t j = 0; j < M; ++j) {
            const int32_t* r = rect_of(j);
            for (int y = r[2]; y < r[3]; ++y)
                for (int x = r[0]; x < r[1]; ++x) c[y * tiles_x + x]++;
        }
    }
    std::vector<int32_t> cursor(ntiles + 1, 0);
    for (int64_t t = 0; t < ntiles; ++t) {
        int32_t tot = 0;
        for (int k = 0; k < nt; ++k) tot += counts[k][t];
        cursor[t + 1] = cursor[t] + tot;
    }
    if (cursor[ntiles] > capacity) return -1;
    std::memcpy(offsets, cursor.data(), sizeof(int32_t) * (ntiles + 1));
    std::vector<int> band(nt + 1, (int)tiles_y);  // rows [band[k], band[k+1]) belong to thread k
    band[0] = 0;
    {
        const int64_t total = cursor[ntiles];
        int k = 1;
        for (int y = 0; y < tiles_y && k < nt; ++y)
            while (k < nt && cursor[(y + 1) * tiles_x] >= total * k / nt) band[k++] = y + 1;
    }
#pragma omp parallel for num_threads(nt) schedule(static, 1)
    for (int k = 0; k < nt; ++k) {
        const int ylo = band[k], yhi = band[k + 1];
        if (ylo >= yhi) continue;
        int32_t* cur = cursor.data();
        for (int64_t j = 0; j < M; ++j) {
            const int32_t* r = rect_of(j);
            const int y0 = std::max<int>(r[2], ylo), y1 = std::min<int>(r[3], yhi);
            const int32_t g = id_of(j);
            for (int y = y0; y < y1; ++y) {
                int32_t* c = cur + y * tiles_x;
                for (int x = r[0]; x < r[1]; ++x) list[c[x]++] = g;
            }
        }
    }
    return offsets[ntiles];
}

}  // namespace

extern "C" {

// gs_bin: order = M visible Gaussian ids sorted by (depth, id); rect: (N, 4) per Gaussian.
int64_t gs_bin(int64_t M, const int64_t* order, const int32_t* rect, int64_t tiles_x, int64_t tiles_y,
               int32_t* offsets, int32_t* list, int64_t capacity, int64_t nthreads) {
    return bin_entries(
        M, [&](int64_t j) { return rect + order[j] * 4; }, [&](int64_t j) { return (int32_t)order[j]; },
        tiles_x, tiles_y, offsets, list, capacity, nthreads);
}


}  // extern "C"

namespace {

inline uint32_t sort_key(float x) {
    uint32_t b = __builtin_bit_cast(uint32_t, x);
    if (b == 0x80000000u) b = 0;  // -0 == +0 (ties by index, as torch.sort)
    return (b & 0x80000000u) ? ~b : (b | 0x80000000u);
}
inline uint64_t sort_key(double x) {
    uint64_t b = __builtin_bit_cast(uint64_t, x);
    if (b == 0x8000000000000000ull) b = 0;
    return (b & 0x8000000000000000ull) ? ~b : (b | 0x8000000000000000ull);
}

// LSD radix sort (stable) of the visible Gaussians by depth; ids ascending on input, so ties keep index order.
template <typename T, typename U>
int64_t depth_order_impl(int64_t N, const uint8_t* visible, const T* depth, const int32_t* rect, int32_t* order,
                         int32_t* rect_sorted) {
    constexpr int BITS = 11, NB = 1 << BITS, PASSES = (int)(sizeof(U) * 8 + BITS - 1) / BITS;
    std::vector<U> key, key2;
    std::vector<int32_t> id, id2;
    key.reserve(N);
    id.reserve(N);
    for (int64_t i = 0; i < N; ++i)
        if (visible[i]) {
            key.push_back(sort_key(depth[i]));
            id.push_back((int32_t)i);
        }
    const int64_t M = (int64_t)key.size();
    key2.resize(M);
    id2.resize(M);
    std::vector<int64_t> hist((size_t)PASSES * NB, 0);
    for (int64_t j = 0; j < M; ++j) {
        const U k = key[j];
        for (int p = 0; p < PASSES; ++p) hist[(size_t)p * NB + ((k >> (p * BITS)) & (NB - 1))]++;
    }
    for (int p = 0; p < PASSES; ++p) {
        int64_t* h = hist.data() + (size_t)p * NB;
        bool trivial = false;
        for (int b = 0; b < NB; ++b)
            if (h[b] == M) trivial = true;
        if (trivial) continue;  // every key has the same digit here
        int64_t run = 0;
        for (int b = 0; b < NB; ++b) {
            const int64_t c = h[b];
            h[b] = run;
            run += c;
        }
        for (int64_t j = 0; j < M; ++j) {
            const int64_t d = h[(key[j] >> (p * BITS)) & (NB - 1)]++;
            key2[d] = key[j];
            id2[d] = id[j];
        }
        key.swap(key2);
        id.swap(id2);
    }
    for (int64_t j = 0; j < M; ++j) {
        if (j + 64 < M) __builtin_prefetch(rect + (int64_t)id[j + 64] * 4, 0, 3);
        order[j] = id[j];
        std::memcpy(rect_sorted + 4 * j, rect + (int64_t)id[j] * 4, 4 * sizeof(int32_t));
    }
    return M;
}

}  // namespace

extern "C" {

// Visible Gaussian ids sorted by (depth, id) into `order` (int32, room for N) and their tile rectangles
// in that order into `rect_sorted` (M, 4). Returns M; `pairs_out` = Σ rectangle areas (tile pairs).
int64_t gs_depth_order(int64_t N, const uint8_t* visible, const void* depth, int64_t dtype, const int32_t* rect,
                       int32_t* order, int32_t* rect_sorted, int64_t* pairs_out) {
    const int64_t M = dtype == 0 ? depth_order_impl<float, uint32_t>(N, visible, (const float*)depth, rect, order, rect_sorted)
                                 : depth_order_impl<double, uint64_t>(N, visible, (const double*)depth, rect, order, rect_sorted);
    int64_t pairs = 0;
    for (int64_t j = 0; j < M; ++j) {
        const int32_t* r = rect_sorted + 4 * j;
        pairs += (int64_t)(r[1] - r[0]) * (int64_t)(r[3] - r[2]);
    }
    *pairs_out = pairs;
    return M;
}

// gs_bin on the output of gs_depth_order: rs holds the rectangles already in depth order, so every
// read is sequential.
int64_t gs_bin_sorted(int64_t M, const int32_t* order, const int32_t* rs, int64_t tiles_x, int64_t tiles_y,
                      int32_t* offsets, int32_t* list, int64_t capacity, int64_t nthreads) {
    return bin_entries(
        M, [&](int64_t j) { return rs + 4 * j; }, [&](int64_t j) { return order[j]; },
        tiles_x, tiles_y, offsets, list, capacity, nthreads);
}

}  // extern "C"
