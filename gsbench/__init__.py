"""gsbench: a benchmark framework for surface-reconstruction Gaussian splatting.

One shared differentiable CPU rasterizer, a plugin registry of methods, official-protocol evaluators
and a uniform runner that writes one JSON record per run. See README.md and docs in the repository.
"""

import os

__version__ = "0.1.0"

# torch and the rasterizer extension each bring an OpenMP runtime; with the default (active) wait
# policy the idle threads of one spin while the other works, which made training 7-10x slower on
# 2 cores. Each runtime reads this when it loads, so it is set here, before anything imports torch.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
