"""The marching-cubes shortcut of `gsbench.methods.neusg.sdf_volume` on finished NeuSG runs (experiments/
neusg_budget/README.md): with the margin scaled by the slope the coarse grid measures (today's) and with the margin of
|∇f| <= 1 (before), the grid vertices whose sign differs from the field evaluated at every vertex, and the time.

    python experiments/neusg_budget/mc_shortcut.py RUN_DIR [RUN_DIR ...]

Each run is loaded from its final checkpoint (`gsbench.runs.finished_run.load_finished_run`) and meshed at its own
voxel (``mesh.voxel_size``), as its extraction does.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch

from gsbench.methods import neusg
from gsbench.runs.finished_run import load_finished_run


def volume(sdf_fn, radius: float, voxel: float, unscaled: bool) -> tuple[np.ndarray, float, float]:
    """(values, spacing, seconds) of `sdf_volume`, its margin unscaled (slope 1) when asked."""
    measured = neusg.coarse_slope
    if unscaled:
        neusg.coarse_slope = lambda grid, step: np.ones([s - 1 for s in grid.shape])
    try:
        start = time.process_time()
        values, spacing = neusg.sdf_volume(sdf_fn, radius, voxel)
        return values, spacing, time.process_time() - start
    finally:
        neusg.coarse_slope = measured


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+")
    args = parser.parse_args()
    for folder in args.runs:
        cfg, scene, method = load_finished_run(folder, "mc_shortcut", load_images=False)
        voxel = cfg.mesh.voxel_size * (1.0 if cfg.mesh.absolute else scene.radius)
        radius = method.field.radius
        with torch.no_grad():
            sdf_fn = lambda x: method.field.sdf(x)[0]  # noqa: E731
            scaled, spacing, scaled_s = volume(sdf_fn, radius, voxel, unscaled=False)
            unscaled, _, unscaled_s = volume(sdf_fn, radius, voxel, unscaled=True)
            n = scaled.shape[0]
            axis = -radius + spacing * np.arange(n)
            start = time.process_time()
            full = np.concatenate([neusg.evaluate(sdf_fn, np.stack(np.meshgrid(axis[i:i + 1], axis, axis, indexing="ij"),
                                                                   -1).reshape(-1, 3)) for i in range(n)])
            full = full.reshape(n, n, n)
            full_s = time.process_time() - start
        coarse = full[::neusg.COARSE, ::neusg.COARSE, ::neusg.COARSE]
        slope = neusg.coarse_slope(coarse, neusg.COARSE * spacing)
        print(f"{cfg.method.get('encoding', 'dense'):5s} {folder}: {n}³ grid; coarse slope median "
              f"{np.median(slope):.2f}, 99th percentile {np.percentile(slope, 99):.2f}, max {slope.max():.2f}; "
              f"signs differing from the full grid: scaled {int(((scaled < 0) != (full < 0)).sum())}, unscaled "
              f"{int(((unscaled < 0) != (full < 0)).sum())}; CPU s: scaled {scaled_s:.0f}, unscaled {unscaled_s:.0f}, "
              f"full {full_s:.0f}", flush=True)
    print(f"load {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
