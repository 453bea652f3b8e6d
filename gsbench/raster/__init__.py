"""The shared differentiable CPU rasterizer (see `gsbench.raster.types` for the contract, docs/rasterizer.md).

``rasterize(gaussians, camera, kernel=..., outputs=...)`` (`gsbench.raster.render`) projects the Gaussians
(`gsbench.raster.projection`: fused C++ with a hand-written backward for every kernel, or PyTorch with
``GSBENCH_PROJECTION=torch``, the reference), sorts the visible ones by depth and bins them into tiles in C++
(`gsbench.raster.binning`), and composites them with the C++/OpenMP tile kernel (`gsbench.raster.composite`,
``csrc/composite.cpp``, built by `gsbench.native.build` through `gsbench.raster.abi`); a
`torch.autograd.Function` connects projection and compositing. ``integrate(...)``
(`gsbench.raster.opacity_field`) evaluates GOF's opacity field at 3D points (no gradient).

``GSBENCH_RASTER=reference`` switches to the slow dense reference (`gsbench.raster.reference`; the switches:
docs/switches.md).
"""

from gsbench.raster.opacity_field import integrate
from gsbench.raster.render import rasterize
from gsbench.raster.types import KERNELS, OUTPUTS, RasterGaussians, RasterSettings, RenderOutput
from gsbench.raster.validation import validate_gaussians

__all__ = [
    "KERNELS",
    "OUTPUTS",
    "RasterGaussians",
    "RasterSettings",
    "RenderOutput",
    "rasterize",
    "integrate",
    "validate_gaussians",
]
