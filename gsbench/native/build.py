"""Compile (on first use) and load the project's C++/OpenMP libraries: the one loader every native kernel goes
through.

Each kernel's sources live with the Python module that calls it (`gsbench.raster.abi`: the rasterizer's
binning, compositing, projection and GOF's opacity integration; `gsbench.losses.ssim`,
`gsbench.losses.normal_consistency`; `gsbench.geometry.eigen3`, `gsbench.geometry.local_geometry`,
`gsbench.geometry.rotations`; `gsbench.methods.sugar_field`, `gsbench.methods.neusg_grid`,
`gsbench.methods.neusg_hash`), each in a ``csrc/`` folder beside it. A
caller asks `load_library` for a library by name with its sources and the ctypes signatures of its entry
points (plain C ABI); the library is compiled with ``torch.utils.cpp_extension.load`` into
``$GSBENCH_CACHE/native`` (default ``~/.cache/gsbench/native``) and loaded once per process. Its file name
carries a hash of the sources, the flags and the CPU, so an edit or another machine triggers a rebuild. The
first build of each library prints one line.
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

import torch

from gsbench.errors import BuildError
from gsbench.switches import CACHE

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
# ctypes signature of an entry point: (argument types, result type)
Signature = tuple[list, type]


def omp_threads() -> int:
    """OpenMP threads for every call into the library: torch's intra-op thread count (at least 1)."""
    return max(1, torch.get_num_threads())


_lock = threading.Lock()
_libraries: dict[str, ctypes.CDLL] = {}


def cache_dir() -> Path:
    """``$GSBENCH_CACHE/native`` (default ``~/.cache/gsbench/native``)."""
    return Path(CACHE.value()).expanduser() / "native"


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


def _digest(sources: list[Path]) -> str:
    """Hash of the sources, the headers beside them, the flags and the CPU."""
    headers = sorted({h for s in sources for h in s.parent.glob("*.h")})
    h = hashlib.sha256()
    for source in [*sources, *headers]:
        h.update(source.read_bytes())
    h.update(" ".join(CFLAGS + LDFLAGS).encode())
    h.update(_cpu_tag().encode())
    return h.hexdigest()[:12]


def _check_compiler() -> None:
    cxx = os.environ.get("CXX", "c++")
    if shutil.which(cxx) is None and shutil.which("g++") is None:
        raise BuildError(
            f"no C++ compiler found (looked for '{cxx}' and 'g++'); the fast kernels are compiled on first use. "
            "Fix: install one (Debian/Ubuntu: apt-get install g++; conda: conda install gxx_linux-64), "
            "or set GSBENCH_RASTER=reference to use the slow pure-PyTorch path"
        )
    if shutil.which("ninja") is None:
        try:
            import ninja  # noqa: F401, PLC0415  (optional: the ninja binary on PATH does the same)
        except ImportError:
            raise BuildError(
                "the 'ninja' build tool is missing (torch.utils.cpp_extension needs it). Fix: pip install ninja"
            ) from None




def load_library(name: str, sources, signatures: dict[str, Signature]) -> ctypes.CDLL:
    """The library ``name`` built from ``sources`` (paths of C++ files) with ``signatures`` ({entry point:
    (argtypes, restype)}) declared; compiled on first use (one line printed), loaded once per process."""
    if name in _libraries:
        return _libraries[name]
    with _lock:
        if name in _libraries:
            return _libraries[name]
        sources = [Path(s) for s in sources]
        tag = f"gsbench_{name}_{_digest(sources)}"
        build_dir = cache_dir() / tag
        so_path = build_dir / f"{tag}.so"
        if not so_path.exists():
            _build(name, tag, sources, build_dir)
        if not so_path.exists():
            raise BuildError(f"the {name} library build finished but {so_path} is missing; delete {build_dir} and retry")
        try:
            lib = ctypes.CDLL(str(so_path))
        except OSError as exc:
            raise BuildError(f"could not load {so_path} ({exc}); delete {build_dir} to force a rebuild") from exc
        for symbol, (argtypes, restype) in signatures.items():
            function = getattr(lib, symbol)
            function.argtypes, function.restype = argtypes, restype
        _libraries[name] = lib
        return lib


def _build(name: str, tag: str, sources: list[Path], build_dir: Path) -> None:
    """Compile ``sources`` into ``build_dir/<tag>.so`` with `CFLAGS` (a `BuildError` naming the fix on failure)."""
    _check_compiler()
    build_dir.mkdir(parents=True, exist_ok=True)
    print(f"gsbench: compiling the C++ {name} library (first use, up to ~20 s) into {build_dir}", file=sys.stderr,
          flush=True)
    try:
        from torch.utils import cpp_extension  # noqa: PLC0415  (setuptools machinery, needed only to compile)

        cpp_extension.load(name=tag, sources=[str(s) for s in sources], extra_cflags=CFLAGS, extra_ldflags=LDFLAGS,
                           build_directory=str(build_dir), is_python_module=False, verbose=False)
    except Exception as exc:  # noqa: BLE001
        raise BuildError(
            f"compiling the C++ {name} library failed ({type(exc).__name__}: {exc}). Fix: check that g++ (>= 9) "
            f"with OpenMP and ninja are installed, delete {build_dir} and retry; or set "
            "GSBENCH_RASTER=reference to use the slow pure-PyTorch path"
        ) from exc
