"""The memory's rate at one and two threads over time, beside torch's fused Adam on the papers'-size parameters.

    python tools/memory_series.py [--rounds 6] [--gaussians 306314] [--pause 2]

Each round, a few seconds apart: `gsbench.bench.roofline.machine_limits` at 1 and 2 threads (the STREAM triad
and the in-place update a += s·c, GB/s) and torch's fused Adam step (``torch._fused_adam_``, the kernel
`gsbench.training.optim.FusedAdam` calls) over six parameter groups of a 3DGS model with ``--gaussians``
Gaussians (positions 3, SH degree 0 3 and rest 45, opacity 1, scales 3, rotations 4 floats each), best of 5
steps, at 1 and 2 threads. Adam reads θ, g, m, v and writes θ, m, v: 28 bytes per parameter. A row per round,
so a bandwidth that changes with the host over minutes shows as it changes (docs/measurements.md, "Adam and
the memory at two threads"). Run it with nothing else on the cores.
"""

from __future__ import annotations

import argparse
import datetime
import time

import torch

from gsbench.bench.roofline import machine_limits

FLOATS_PER_GAUSSIAN = (3, 3, 45, 1, 3, 4)
ADAM_BYTES_PER_PARAMETER = 28


def adam_step_seconds(groups: list[tuple], threads: int, repeats: int = 5) -> float:
    """Best seconds of ``repeats`` fused Adam steps over ``groups`` (param, grad, exp_avg, exp_avg_sq, step)."""
    torch.set_num_threads(threads)
    best = float("inf")
    for _ in range(repeats + 1):
        start = time.perf_counter()
        for param, grad, exp_avg, exp_avg_sq, step in groups:
            torch._fused_adam_([param], [grad], [exp_avg], [exp_avg_sq], [], [step], lr=1e-3, beta1=0.9, beta2=0.999,
                               weight_decay=0.0, eps=1e-15, amsgrad=False, maximize=False)
        best = min(best, time.perf_counter() - start)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--gaussians", type=int, default=306_314)
    parser.add_argument("--pause", type=float, default=2.0, help="seconds between rounds")
    args = parser.parse_args()
    sizes = [args.gaussians * k for k in FLOATS_PER_GAUSSIAN]
    groups = [(torch.randn(n), torch.randn(n), torch.zeros(n), torch.zeros(n), torch.tensor(1.0)) for n in sizes]
    adam_bytes = sum(sizes) * ADAM_BYTES_PER_PARAMETER
    for _ in range(args.rounds):
        two, one = machine_limits(2, fma_iters=1_000_000), machine_limits(1, fma_iters=1_000_000)
        adam_one, adam_two = adam_step_seconds(groups, 1), adam_step_seconds(groups, 2)
        print(f"{datetime.datetime.now():%H:%M:%S} triad 1t {one['bandwidth_gb_s']:.0f} 2t {two['bandwidth_gb_s']:.0f}"
              f" GB/s | update 1t {one['update_gb_s']:.0f} 2t {two['update_gb_s']:.0f} GB/s | Adam 1t "
              f"{adam_one * 1e3:.2f} ms ({adam_bytes / adam_one / 1e9:.0f} GB/s) 2t {adam_two * 1e3:.2f} ms "
              f"({adam_bytes / adam_two / 1e9:.0f} GB/s) = {adam_one / adam_two:.2f}x", flush=True)
        time.sleep(args.pause)


if __name__ == "__main__":
    main()
