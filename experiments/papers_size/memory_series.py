"""The memory's rate at one and two threads over time, beside torch's fused Adam on the papers'-size parameters.

    python experiments/papers_size/memory_series.py [--rounds 6] [--gaussians 306314] [--pause 2]

Each round, a few seconds apart: `gsbench.bench.roofline.machine_limits` at 1 and 2 threads (the STREAM triad
and the in-place update a += s·c, GB/s) and `gsbench.training.optim.FusedAdam`'s step (torch's fused kernel)
over six parameter groups of a 3DGS model with ``--gaussians`` Gaussians (positions 3, SH degree 0 3 and rest
45, opacity 1, scales 3, rotations 4 floats each), best of 5 steps, at 1 and 2 threads. Adam reads θ, g, m, v
and writes θ, m, v: 28 bytes per parameter. A row per round, so a bandwidth that changes with the host over
minutes shows as it changes (experiments/papers_size/README.md, "Adam and the memory at two threads"). Run it with
nothing else on the cores.
"""

from __future__ import annotations

import argparse
import datetime
import time

import torch

from gsbench.bench.roofline import machine_limits
from gsbench.training.optim import FusedAdam

FLOATS_PER_GAUSSIAN = (3, 3, 45, 1, 3, 4)
ADAM_BYTES_PER_PARAMETER = 28


def adam_step_seconds(optimizer: FusedAdam, threads: int, repeats: int = 5) -> float:
    """Best seconds of ``repeats`` steps of ``optimizer`` (its gradients set) at ``threads`` threads."""
    torch.set_num_threads(threads)
    best = float("inf")
    for _ in range(repeats + 1):
        start = time.perf_counter()
        optimizer.step()
        best = min(best, time.perf_counter() - start)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--gaussians", type=int, default=306_314)
    parser.add_argument("--pause", type=float, default=2.0, help="seconds between rounds")
    args = parser.parse_args()
    sizes = [args.gaussians * k for k in FLOATS_PER_GAUSSIAN]
    params = [torch.nn.Parameter(torch.randn(n)) for n in sizes]
    for param in params:
        param.grad = torch.randn_like(param)
    optimizer = FusedAdam([{"params": [p]} for p in params], lr=1e-3, eps=1e-15)
    optimizer.step()  # the first step creates the moments (torch's own step)
    adam_bytes = sum(sizes) * ADAM_BYTES_PER_PARAMETER
    for _ in range(args.rounds):
        two, one = machine_limits(2, fma_iters=1_000_000), machine_limits(1, fma_iters=1_000_000)
        adam_one, adam_two = adam_step_seconds(optimizer, 1), adam_step_seconds(optimizer, 2)
        print(f"{datetime.datetime.now():%H:%M:%S} triad 1t {one['bandwidth_gb_s']:.0f} 2t {two['bandwidth_gb_s']:.0f}"
              f" GB/s | update 1t {one['update_gb_s']:.0f} 2t {two['update_gb_s']:.0f} GB/s | Adam 1t "
              f"{adam_one * 1e3:.2f} ms ({adam_bytes / adam_one / 1e9:.0f} GB/s) 2t {adam_two * 1e3:.2f} ms "
              f"({adam_bytes / adam_two / 1e9:.0f} GB/s) = {adam_one / adam_two:.2f}x", flush=True)
        time.sleep(args.pause)


if __name__ == "__main__":
    main()
