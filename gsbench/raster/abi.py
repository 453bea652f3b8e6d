"""The rasterizer's native library: its C++ sources (``csrc/``), the ctypes mirrors of their argument
structs and the signatures of their entry points.

``csrc/sort_bin.cpp`` sorts the visible Gaussians by depth and lists them per tile by their rectangles,
``csrc/bin_exact.cpp`` by the exact ellipse/tile overlap (ewa, rade), ``csrc/composite.cpp`` composites
them (forward and backward; ``csrc/raster_common.h`` holds what the three share); ``csrc/solid.cpp`` is GGGS's stochastic-solid
median depth after the compositing; ``csrc/project.cpp`` is
the fused EWA-family projection; ``csrc/integrate.cpp`` evaluates GOF's opacity field at 3D points. They are built as one library by `gsbench.native.build`.
"""

from __future__ import annotations

import ctypes
from pathlib import Path

from gsbench.native.build import load_library

CSRC = Path(__file__).parent / "csrc"
SOURCES = ("composite.cpp", "sort_bin.cpp", "bin_exact.cpp", "integrate.cpp", "project.cpp", "solid.cpp")  # + raster_common.h


class GsArgs(ctypes.Structure):
    """Mirror of ``struct GsArgs`` in csrc/raster_common.h (8-byte fields only)."""

    _fields_ = [
        (name, ctypes.c_int64)
        for name in (
            "kernel", "dtype", "width", "height", "tiles_x", "tiles_y", "n_gauss", "n_params", "nthreads",
            "want_rgb", "want_depth", "want_median", "want_normal", "want_dist", "detach_dist",
        )
    ] + [(name, ctypes.c_double) for name in ("fx", "fy", "cx", "cy", "near_z", "far_z", "surfel_k")] + [
        (name, ctypes.c_void_p)
        for name in (
            "params", "bounds", "depth_key", "tile_offsets", "tile_list",
            "out_rgb", "out_alpha", "out_depth", "out_median", "out_normal", "out_dist",
            "T_final", "last", "median_idx", "M1", "M2",
            "g_rgb", "g_alpha", "g_depth", "g_median", "g_normal", "g_dist",
            "grad_params", "absgrad", "proxy",
        )
    ] + [("pairs", ctypes.c_int64)] + [
        # plane_distance (PGSR, docs/methods/pgsr.md §3.1): appended so the older fields keep their offsets
        ("want_plane", ctypes.c_int64), ("plane_d", ctypes.c_void_p), ("out_plane", ctypes.c_void_p),
        ("g_plane", ctypes.c_void_p), ("grad_plane", ctypes.c_void_p),
    ]


class SolidArgs(ctypes.Structure):
    """Mirror of ``struct SolidArgs`` in csrc/solid.cpp (8-byte fields only)."""

    _fields_ = [
        (name, ctypes.c_int64)
        for name in ("dtype", "width", "height", "tiles_x", "tiles_y", "n_gauss", "nthreads", "rounds")
    ] + [(name, ctypes.c_double) for name in ("search_range", "min_transmittance")] + [
        (name, ctypes.c_void_p)
        for name in ("params", "bounds", "tile_offsets", "tile_list", "last", "T_final", "inv_sigma", "out_t", "g_t",
                     "grad_params", "grad_inv_sigma", "absgrad")
    ] + [("pairs", ctypes.c_int64)]


class ProjArgs(ctypes.Structure):
    """Mirror of ``struct ProjArgs`` in csrc/project.cpp (8-byte fields and fixed double arrays only)."""

    _fields_ = [
        (name, ctypes.c_int64)
        for name in ("n", "dtype", "kernel", "sh_degree", "sh_k", "has_filter", "width", "height", "tile", "gx", "gy",
                     "nthreads")
    ] + [(name, ctypes.c_double) for name in ("fx", "fy", "cx", "cy", "near_z", "eps2d", "aa", "limx", "limy")] + [
        ("R", ctypes.c_double * 9), ("t", ctypes.c_double * 3), ("C", ctypes.c_double * 3), ("L", ctypes.c_double * 16),
    ] + [
        (name, ctypes.c_void_p)
        for name in (
            "means", "quats", "scales", "opac", "sh", "filter3d",
            "params", "means2d", "radii", "visible", "depth", "bounds", "rect", "rect_radius",
            "g_params", "g_means", "g_quats", "g_scales", "g_opac", "g_sh",
        )
    ] + [("surfel_k", ctypes.c_double), ("sh_rest_k", ctypes.c_int64), ("sh_rest", ctypes.c_void_p),
         ("g_sh_rest", ctypes.c_void_p)]


_i64, _ptr, _int = ctypes.c_int64, ctypes.c_void_p, ctypes.c_int
_BIN = [_i64, _ptr, _ptr, _i64, _i64, _ptr, _ptr, _i64, _i64]
SIGNATURES = {
    "gs_forward": ([ctypes.POINTER(GsArgs)], _int),
    "gs_backward": ([ctypes.POINTER(GsArgs)], _int),
    "gs_solid_forward": ([ctypes.POINTER(SolidArgs)], _int),
    "gs_solid_backward": ([ctypes.POINTER(SolidArgs)], _int),
    "gs_bin": (_BIN, _i64),
    "gs_bin_sorted": (_BIN, _i64),
    "gs_depth_order": ([_i64, _ptr, _ptr, _i64, _ptr, _ptr, _ptr, ctypes.POINTER(ctypes.c_int64)], _i64),
    "gs_bin_exact_count": ([_i64, _ptr, _ptr, _i64, _ptr, _ptr, _ptr, _i64, _i64, _i64, _i64, _i64, _i64, _ptr, _ptr,
                            _ptr, _ptr, _i64, _ptr], _i64),
    "gs_bin_exact_fill": ([_i64, _ptr, _ptr, _ptr, _ptr, _i64, _i64, _i64, _i64, _i64, _i64, _ptr, _ptr, _ptr, _ptr,
                           _i64, _i64, _ptr], _i64),
    "gs_integrate": ([_ptr], _int),
    "gs_integrate_cells": ([_ptr], _int),
    "gs_project_forward": ([ctypes.POINTER(ProjArgs)], _int),
    "gs_project_backward": ([ctypes.POINTER(ProjArgs)], _int),
}


def library() -> ctypes.CDLL:
    """The rasterizer's library (compiled on first use)."""
    return load_library("raster", [CSRC / s for s in SOURCES], SIGNATURES)
