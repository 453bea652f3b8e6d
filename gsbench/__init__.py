"""gsbench: a benchmark framework for surface-reconstruction Gaussian splatting.

One shared differentiable CPU rasterizer, a plugin registry of methods, official-protocol evaluators
and a uniform runner that writes one JSON record per run. See README.md and docs in the repository.
"""

__version__ = "0.1.0"
