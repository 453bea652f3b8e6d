"""Per-Gaussian quantities of one view (`gsbench.raster.payload.Projection`): the fused C++ pass
(`gsbench.raster.projection_fused`) or its vectorised PyTorch oracle (`gsbench.raster.projection_torch`).

`project(gaussians, camera, kernel, settings)` runs the fused projection for every kernel (ewa, rade,
raymax, surfel) unless ``GSBENCH_PROJECTION=torch`` or ``projection.IMPL = "torch"``.
"""

from __future__ import annotations

import os

from gsbench.data.camera import Camera
from gsbench.raster.payload import Projection
from gsbench.raster.projection_fused import FUSED_KERNELS, project_fused
from gsbench.raster.projection_torch import project_torch
from gsbench.raster.types import RasterGaussians, RasterSettings

# Which projection `project` uses: "fused" (C++, csrc/project.cpp) or "torch" (this module's vectorised
# PyTorch, also the oracle of the fused one). None = the GSBENCH_PROJECTION environment variable,
# default "fused".
IMPL: str | None = None


def projection_impl(kernel: str) -> str:
    """"fused" or "torch": the projection `project` will use for ``kernel``."""
    impl = IMPL if IMPL is not None else os.environ.get("GSBENCH_PROJECTION", "fused")
    impl = impl.strip().lower() or "fused"
    if impl not in ("fused", "torch"):
        raise ValueError(f"GSBENCH_PROJECTION / projection.IMPL must be 'fused' or 'torch', got '{impl}'")
    return impl if kernel in FUSED_KERNELS else "torch"


def project(gaussians: RasterGaussians, camera: Camera, kernel: str, settings: RasterSettings) -> Projection:
    """Per-Gaussian projection of one view (fused C++ unless disabled, else PyTorch)."""
    if projection_impl(kernel) == "fused":
        return project_fused(gaussians, camera, kernel, settings)
    return project_torch(gaussians, camera, kernel, settings)
