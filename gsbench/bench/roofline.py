"""The machine's limits and how far each rasterizer phase is from them (`gsbench bench raster`), as
docs/rasterizer.md §12.3 states it: a phase's bound is min(peak / operations, bandwidth / bytes) items per second,
and `annotate` divides the measured rate by it.

`machine_limits(threads)` measures the STREAM triad a = b + s·c over three 64 MiB float32 arrays (12 bytes an
element, as STREAM counts), the in-place update a += s·c (an optimizer's pattern: a triad's write first reads the
line it writes, an update does not, so it shows the most a stream can draw) and the float32 FMA peak of 16
independent 16-wide chains per thread (`csrc/roofline.cpp`). `PHASE_MODEL`'s per-item counts are estimates from
the source (± a fifth): a phase at 80% of its bound has little left, one at 10% has a lot.
"""

from __future__ import annotations

import ctypes
from pathlib import Path

import numpy as np

from gsbench.native.build import load_library

TRIAD_ELEMENTS = 16 * 2**20  # 64 MiB per float32 array: far beyond any cache here
TRIAD_BYTES_PER_ELEMENT = 12
FMA_ITERS = 10_000_000
FMA_REPEATS = 3  # best of: the probe's clock ramps up and other processes may take the cores
FMA_LANE_OPS = 16 * 16  # per iteration and thread: 16 chains × 16 lanes

# Per item: (what an item is, lane operations, DRAM bytes). Compositing lanes: the kernel's evaluation (the
# exponential counted as its 29 polynomial operations) plus the blend; their payload reads hit the cache
# (one Gaussian's 52-96 bytes serve up to 256 lanes), so their DRAM bytes per lane are about 0.3. The
# projection reads means, quaternion, scales, opacity and degree-0 SH (56 bytes) and writes the payload,
# the centre, radius, visibility, depth, box and two rectangles (120-165 bytes).
PHASE_MODEL = {
    "projection": ("gaussian", {"ewa": 260, "rade": 330, "raymax": 420, "surfel": 300},
                   {"ewa": 180, "rade": 190, "raymax": 225, "surfel": 210}),
    "projection_bwd": ("gaussian", {"ewa": 520, "rade": 660, "raymax": 840, "surfel": 600},
                       {"ewa": 300, "rade": 310, "raymax": 370, "surfel": 350}),
    "sort_bin": ("tile entry", {k: 40 for k in ("ewa", "rade", "raymax", "surfel")},
                 {k: 64 for k in ("ewa", "rade", "raymax", "surfel")}),
    "raster_fwd": ("lane", {"ewa": 70, "rade": 75, "raymax": 85, "surfel": 90},
                   {k: 0.3 for k in ("ewa", "rade", "raymax", "surfel")}),
    "raster_bwd": ("lane", {"ewa": 105, "rade": 115, "raymax": 150, "surfel": 150},
                   {k: 0.6 for k in ("ewa", "rade", "raymax", "surfel")}),
}


def _library() -> ctypes.CDLL:
    signatures = {
        "gs_triad_seconds": ([ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int,
                              ctypes.c_int], ctypes.c_double),
        "gs_update_seconds": ([ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int, ctypes.c_int],
                              ctypes.c_double),
        "gs_fma_seconds": ([ctypes.c_int64, ctypes.c_int, ctypes.c_void_p], ctypes.c_double),
    }
    return load_library("roofline", [Path(__file__).parent / "csrc" / "roofline.cpp"], signatures)


def machine_limits(threads: int, elements: int = TRIAD_ELEMENTS, fma_iters: int = FMA_ITERS) -> dict:
    """{"bandwidth_gb_s", "update_gb_s", "peak_lane_ops_s", "peak_gflops", "threads"} measured now (module
    docstring)."""
    lib = _library()
    a, b, c = (np.ones(elements, np.float32) for _ in range(3))
    seconds = lib.gs_triad_seconds(a.ctypes.data, b.ctypes.data, c.ctypes.data, elements, 5, threads)
    bandwidth = TRIAD_BYTES_PER_ELEMENT * elements / seconds
    update = TRIAD_BYTES_PER_ELEMENT * elements / lib.gs_update_seconds(a.ctypes.data, c.ctypes.data, elements, 5,
                                                                         threads)
    sink = np.zeros(1, np.float32)
    fma = min(lib.gs_fma_seconds(fma_iters, threads, sink.ctypes.data) for _ in range(FMA_REPEATS))
    lane_ops = threads * fma_iters * FMA_LANE_OPS / fma
    return {"threads": threads, "bandwidth_gb_s": bandwidth / 1e9, "update_gb_s": update / 1e9,
            "peak_lane_ops_s": lane_ops,
            "peak_gflops": 2 * lane_ops / 1e9}


def annotate(row: dict, machine: dict) -> list[dict]:
    """Per phase of one `gsbench bench raster` row: items per second measured, the model's bound and its
    limit (compute or memory), and the fraction of the bound reached."""
    kernel = row["kernel"]
    items = {"gaussian": row["n"], "tile entry": row["tile_pairs_x256"] / 256, "lane": None}
    out = []
    for phase, (unit, ops, mem) in PHASE_MODEL.items():
        ms = row["phases_ms"].get(phase, 0.0)
        count = items[unit] if unit != "lane" else (row["pairs_fwd"] if phase == "raster_fwd" else row["pairs_bwd"])
        if ms <= 0 or not count:
            continue
        rate = count / (ms / 1e3)
        compute = machine["peak_lane_ops_s"] / ops[kernel]
        memory = machine["bandwidth_gb_s"] * 1e9 / mem[kernel]
        bound = min(compute, memory)
        out.append({"phase": phase, "item": unit, "per_s": rate, "ops": ops[kernel], "bytes": mem[kernel],
                    "bound_per_s": bound, "limit": "compute" if compute <= memory else "memory",
                    "fraction": rate / bound})
    return out


def format_roofline(result: dict) -> str:
    """The machine's limits and, per kernel × workload and phase, the fraction of the bound reached."""
    m = result["machine"]
    lines = [f"machine ({m['threads']} threads): memory {m['bandwidth_gb_s']:.1f} GB/s (triad), "
             f"{m['update_gb_s']:.1f} GB/s (in-place update), "
             f"peak {m['peak_gflops']:.0f} GFLOP/s float32 FMA ({m['peak_lane_ops_s'] / 1e9:.0f} G lane-ops/s)",
             "phase bounds (items/s measured / bound, limit): "]
    for row in result["rows"]:
        parts = [f"{p['phase']} {p['per_s']:.3g}/{p['bound_per_s']:.3g} {p['item']}/s "
                 f"({100 * p['fraction']:.0f}%, {p['limit']})" for p in row.get("roofline", [])]
        lines.append(f"  {row['kernel']:6s} {row['workload']}: " + "; ".join(parts))
    return "\n".join(lines)
