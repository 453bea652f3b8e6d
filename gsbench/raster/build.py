"""Compile (on first use) and load the C++/OpenMP rasterizer.

The extension has a plain C ABI (raster.cpp: binning and compositing; integrate.cpp; project.cpp: the
fused EWA-family projection; eigen3.cpp: the batched symmetric 3×3 eigen-solver of `gsbench.geometry.eigen3`;
ssim.cpp: the fused SSIM map and its backward of `gsbench.ssim`; sugar_field.cpp: SuGaR's neighbour field
and normal average and their backwards of `gsbench.methods.sugar_field`; normal_consistency.cpp: the
depth-normal consistency term and its backward of `gsbench.normal_consistency`; local_covariance.cpp:
IBGS's kNN neighbourhood covariance and its backward of `gsbench.geometry.local_geometry`; frames.cpp: its
frame alignment and the no-gradient rotation → quaternion of `gsbench.geometry.rotations`), compiled with
``torch.utils.cpp_extension.load`` into ``$GSBENCH_CACHE/raster`` (default ``~/.cache/gsbench/raster``)
and called through ctypes. The library name carries a hash of the sources, the flags and the CPU, so
an edit or another machine triggers a rebuild. The first build prints one line.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import sys
import threading
from pathlib import Path

from gsbench.errors import BuildError

CSRC = Path(__file__).parent / "csrc"
SOURCES = ["raster.cpp", "integrate.cpp", "project.cpp", "eigen3.cpp", "ssim.cpp", "sugar_field.cpp",
           "normal_consistency.cpp", "local_covariance.cpp", "frames.cpp"]
CFLAGS = [
    "-O3",
    "-march=native",
    "-mprefer-vector-width=512",
    "-fopenmp",
    "-fno-trapping-math",
    "-fno-math-errno",
    "-ffinite-math-only",
    "-fno-signed-zeros",
    "-std=c++17",
]
LDFLAGS = ["-fopenmp"]

def omp_threads() -> int:
    """OpenMP threads for every call into the library: torch's intra-op thread count (at least 1)."""
    import torch  # noqa: PLC0415

    return max(1, torch.get_num_threads())


_lock = threading.Lock()
_lib = None


class GsArgs(ctypes.Structure):
    """Mirror of ``struct GsArgs`` in csrc/raster.cpp (8-byte fields only)."""

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


def cache_dir() -> Path:
    root = os.environ.get("GSBENCH_CACHE")
    base = Path(root) if root else Path.home() / ".cache" / "gsbench"
    return base / "raster"


def _cpu_tag() -> str:
    flags = ""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("flags"):
                    flags = line
                    break
    except OSError:
        pass
    return platform.machine() + flags


def _digest() -> str:
    h = hashlib.sha256()
    for name in SOURCES:
        h.update((CSRC / name).read_bytes())
    h.update(" ".join(CFLAGS + LDFLAGS).encode())
    h.update(_cpu_tag().encode())
    return h.hexdigest()[:12]


def _check_compiler() -> None:
    cxx = os.environ.get("CXX", "c++")
    if shutil.which(cxx) is None and shutil.which("g++") is None:
        raise BuildError(
            f"no C++ compiler found (looked for '{cxx}' and 'g++'); the fast rasterizer is compiled on first use. "
            "Fix: install one (Debian/Ubuntu: apt-get install g++; conda: conda install gxx_linux-64), "
            "or set GSBENCH_RASTER=reference to use the slow pure-PyTorch path"
        )
    if shutil.which("ninja") is None:
        try:
            import ninja  # noqa: F401, PLC0415
        except ImportError:
            raise BuildError(
                "the 'ninja' build tool is missing (torch.utils.cpp_extension needs it). Fix: pip install ninja"
            ) from None


def load_library() -> ctypes.CDLL:
    """The loaded extension; compiles it on first use (one line printed)."""
    global _lib
    if _lib is not None:
        return _lib
    with _lock:
        if _lib is not None:
            return _lib
        name = f"gsbench_raster_{_digest()}"
        build_dir = cache_dir() / name
        so_path = build_dir / f"{name}.so"
        if not so_path.exists():
            _check_compiler()
            build_dir.mkdir(parents=True, exist_ok=True)
            print(f"gsbench: compiling the C++ rasterizer (first use, ~20 s) into {build_dir}", file=sys.stderr, flush=True)
            try:
                from torch.utils import cpp_extension  # noqa: PLC0415

                cpp_extension.load(
                    name=name,
                    sources=[str(CSRC / s) for s in SOURCES],
                    extra_cflags=CFLAGS,
                    extra_ldflags=LDFLAGS,
                    build_directory=str(build_dir),
                    is_python_module=False,
                    verbose=False,
                )
            except Exception as exc:  # noqa: BLE001
                raise BuildError(
                    f"compiling the C++ rasterizer failed ({type(exc).__name__}: {exc}). Fix: check that g++ (>= 9) "
                    f"with OpenMP and ninja are installed, delete {build_dir} and retry; or set "
                    "GSBENCH_RASTER=reference to use the slow pure-PyTorch path"
                ) from exc
        if not so_path.exists():
            raise BuildError(f"the rasterizer build finished but {so_path} is missing; delete {build_dir} and retry")
        try:
            lib = ctypes.CDLL(str(so_path))
        except OSError as exc:
            raise BuildError(f"could not load {so_path} ({exc}); delete {build_dir} to force a rebuild") from exc
        lib.gs_forward.argtypes = [ctypes.POINTER(GsArgs)]
        lib.gs_forward.restype = ctypes.c_int
        lib.gs_backward.argtypes = [ctypes.POINTER(GsArgs)]
        lib.gs_backward.restype = ctypes.c_int
        lib.gs_bin.argtypes = [
            ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64,
            ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64,
        ]
        lib.gs_bin.restype = ctypes.c_int64
        lib.gs_depth_order.argtypes = [
            ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p,
            ctypes.c_void_p, ctypes.POINTER(ctypes.c_int64),
        ]
        lib.gs_depth_order.restype = ctypes.c_int64
        lib.gs_bin_sorted.argtypes = lib.gs_bin.argtypes
        lib.gs_bin_sorted.restype = ctypes.c_int64
        for fn in (lib.gs_integrate, lib.gs_integrate_cells):
            fn.argtypes = [ctypes.c_void_p]
            fn.restype = ctypes.c_int
        for fn in (lib.gs_project_forward, lib.gs_project_backward):
            fn.argtypes = [ctypes.POINTER(ProjArgs)]
            fn.restype = ctypes.c_int
        lib.gs_sym3_eigh_forward.argtypes = [ctypes.c_int64] + [ctypes.c_void_p] * 3 + [ctypes.c_int64]
        lib.gs_sym3_eigh_forward.restype = ctypes.c_int
        lib.gs_sym3_eigh_backward.argtypes = [ctypes.c_int64] + [ctypes.c_void_p] * 4 + [ctypes.c_double] * 2 + [
            ctypes.c_void_p, ctypes.c_int64,
        ]
        lib.gs_sym3_eigh_backward.restype = ctypes.c_int
        lib.gs_ssim_forward.argtypes = [ctypes.c_int64] * 4 + [ctypes.c_void_p] * 3 + [ctypes.c_double] * 2 + [
            ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64,
        ]
        lib.gs_ssim_forward.restype = ctypes.c_int
        lib.gs_ssim_backward.argtypes = [ctypes.c_int64] * 4 + [ctypes.c_void_p] * 6 + [ctypes.c_int64]
        lib.gs_ssim_backward.restype = ctypes.c_int
        maps = [ctypes.c_int64] * 3 + [ctypes.c_void_p] * 4 + [ctypes.c_double] * 2 + [ctypes.c_int64] + [ctypes.c_double] * 4
        lib.gs_normal_consistency_forward.argtypes = maps + [ctypes.POINTER(ctypes.c_double), ctypes.c_int64]
        lib.gs_normal_consistency_forward.restype = ctypes.c_int
        lib.gs_normal_consistency_backward.argtypes = maps + [ctypes.c_double] + [ctypes.c_void_p] * 3 + [ctypes.c_int64]
        lib.gs_normal_consistency_backward.restype = ctypes.c_int
        lib.gs_local_covariance_forward.argtypes = [ctypes.c_int64] * 4 + [ctypes.c_void_p] * 2 + [ctypes.c_double] + [
            ctypes.c_void_p, ctypes.c_int64,
        ]
        lib.gs_local_covariance_forward.restype = ctypes.c_int
        lib.gs_local_covariance_backward.argtypes = [ctypes.c_int64] * 4 + [ctypes.c_void_p] * 4 + [ctypes.c_int64]
        lib.gs_local_covariance_backward.restype = ctypes.c_int
        lib.gs_frame_alignment.argtypes = [ctypes.c_int64] * 2 + [ctypes.c_void_p] * 2 + [ctypes.c_int64] + [
            ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64,
        ]
        lib.gs_frame_alignment.restype = ctypes.c_int
        lib.gs_rotmat_to_quat.argtypes = [ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64]
        lib.gs_rotmat_to_quat.restype = ctypes.c_int
        lib.gs_rotmat_to_quat_backward.argtypes = [ctypes.c_int64] + [ctypes.c_void_p] * 3 + [ctypes.c_int64]
        lib.gs_rotmat_to_quat_backward.restype = ctypes.c_int
        _lib = lib
        return lib
