"""gsbench: a benchmark framework for surface-reconstruction Gaussian splatting.

One shared differentiable CPU rasterizer, a plugin registry of methods, official-protocol evaluators
and a uniform runner that writes one JSON record per run. See README.md and docs in the repository.
"""

import ctypes
import os

__version__ = "0.1.0"

# torch and the rasterizer extension each bring an OpenMP runtime; with the default (active) wait
# policy the idle threads of one spin while the other works, which made training 7-10x slower on
# 2 cores. Each runtime reads this when it loads, so it is set here, before anything imports torch.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _load_libusb() -> None:
    """open3d's library needs the system library libusb-1.0 (soname ``libusb-1.0.so.0``), which a fresh
    Debian/Ubuntu lacks. When the system has none, load the copy the ``libusb-package`` wheel ships (a
    dependency on Linux) with ``RTLD_GLOBAL``, before anything imports open3d: the dynamic loader then finds
    that soname already loaded. With neither, `gsbench.errors.import_open3d` names the fix."""
    try:
        ctypes.CDLL("libusb-1.0.so.0")
        return
    except OSError:
        pass
    try:
        import libusb_package  # noqa: PLC0415  (optional: only where the system library is missing)
    except ImportError:
        return
    path = libusb_package.get_library_path()
    if path:
        ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)


_load_libusb()
