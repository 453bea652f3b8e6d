// The cell of a point on one axis of a level of resolution N, shared by NeuSG's dense and hash grid encodings
// (neusg_grid.cpp, neusg_hash.cpp): s = min(max(u N, 0), N), i = min(floor(s), N − 1), t = s − i.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

// Fewer points than this run on the calling thread (a parallel region costs more than they do).
constexpr int64_t MIN_PARALLEL = 2048;

struct Axis {
    int64_t i;   // cell index in [0, N − 1]
    double t;    // position in the cell, [0, 1]
};

inline Axis axis(double u, int64_t n) {
    const double s = std::min(std::max(u * double(n), 0.0), double(n));
    int64_t i = (int64_t)std::floor(s);
    i = std::min(std::max(i, int64_t(0)), n - 1);
    return {i, s - double(i)};
}
