"""Per-Gaussian quantities of one view (`gsbench.raster.payload.Projection`): the fused C++ pass
(`gsbench.raster.projection_fused`) or its vectorised PyTorch oracle (`gsbench.raster.projection_torch`).

`project(gaussians, camera, kernel, settings)` runs the fused projection for every kernel (ewa, rade,
raymax, surfel) unless ``GSBENCH_PROJECTION=torch`` (`gsbench.switches`).
"""

from __future__ import annotations

from gsbench.data.camera import Camera
from gsbench.raster.payload import Projection
from gsbench.raster.projection_fused import FUSED_KERNELS, project_fused
from gsbench.raster.projection_torch import project_torch
from gsbench.raster.types import RasterGaussians, RasterSettings
from gsbench.switches import PROJECTION


def projection_impl(kernel: str) -> str:
    """"fused" or "torch": the projection `project` will use for ``kernel``."""
    impl = PROJECTION.value()
    return impl if kernel in FUSED_KERNELS else "torch"


def project(gaussians: RasterGaussians, camera: Camera, kernel: str, settings: RasterSettings) -> Projection:
    """Per-Gaussian projection of one view (fused C++ unless disabled, else PyTorch)."""
    if projection_impl(kernel) == "fused":
        return project_fused(gaussians, camera, kernel, settings)
    return project_torch(gaussians, camera, kernel, settings)
