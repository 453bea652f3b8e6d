"""What a preset's protocol costs per run and per suite, on one machine and on a cluster of such machines.

    python tools/preset_cost.py --bench BENCH.json --anchor RECORD.json [--anchor-code-factor F]
                                [--scenes 7] [--seeds 1 3] [--machines 1 16] [--cores 2]
    python tools/preset_cost.py --bench BENCH.json --anchor RECORD.json [--anchor-code-factor F]
                                --suite dtu 15 800x600-300k --suite tnt 6 800x600-1m 1.11
                                --seeds 3 --cores 16 [--nodes 4 16 64] [--skip METHOD ...]

Estimated from two measurements on the same machine (experiments/paper_preset/README.md, "What the papers' protocol
costs"):

- ``--anchor``: one finished run of the preset (its ``record.json``). Its training's CPU time T_a
  (``timings.train_cpu``: one thread, so the cost on a free core whatever else ran beside it), and its mesh
  extraction, evaluation and loading (``timings.extract + evaluate + load``, wall seconds) as E.
- ``--bench``: ``gsbench --threads 1 bench train --workloads <m>-800x600-300k ... --json BENCH.json`` for the
  methods to cost, the anchor's method among them. s_m is method m's step there (ms).

A run of method m then trains for T_m = F · T_a · s_m / s_a CPU-seconds, where s_a is the anchor method's bench
step and F (``--anchor-code-factor``, default 1) converts the anchor's code to the bench's: the anchor method's
step at the bench's commit over its step at the anchor's, both from ``bench train --run`` on the anchor's own
checkpoint. Two assumptions, stated with the table: the ratio of two methods' steps on the bench's state (random
Gaussians early in the schedule) holds over a whole run, and every method's meshing and evaluation cost E. A
second finished run checks the first against its prediction.

A suite is ``scenes × seeds`` runs of each method. On M machines of C cores each, one run per core at one thread:
the makespan of longest-first list scheduling of all the suite's runs on M·C slots (a run is not split).

The cluster table (``--suite NAME SCENES SIZE [PIXELS]``, once per suite; docs/cluster.md §6): the suite's method m
trains for T_m = F · T_a · s_m(SIZE) / s_a(``--anchor-size``) · PIXELS, where s_m(SIZE) is the bench step of workload
``<m>-SIZE`` (every method the bench has at that size, less ``--skip``) and PIXELS the suite's image pixels over the
workload's (default 1). Per suite and for all of them together: runs (scenes × seeds × methods), core-hours (the
runs' sum), node-hours (core-hours / ``--cores``, the cores of a node, each busy), the longest run (which bounds
the wall time however many nodes) and the wall time on each of ``--nodes`` nodes (list scheduling, as above, on
nodes × cores slots). Assumed besides the two above: a node's cores run one run each at the bench's single-thread
speed (no memory-bandwidth contention between them), and a suite's image size scales the step by PIXELS.
"""

from __future__ import annotations

import argparse
import heapq
import json
from pathlib import Path


def list_schedule_makespan(durations: list[float], slots: int) -> float:
    """Makespan of longest-processing-time-first list scheduling of ``durations`` on ``slots`` identical slots."""
    loads = [0.0] * slots
    heapq.heapify(loads)
    for d in sorted(durations, reverse=True):
        heapq.heappush(loads, heapq.heappop(loads) + d)
    return max(loads)


def run_costs(bench: dict, anchor: dict, code_factor: float) -> dict[str, dict]:
    """Per method of ``bench``: its bench step (ms) and a run's estimated train CPU-s and total s."""
    steps = {r["method"]: r["step_ms"] for r in bench["result"]["results"]}
    method = anchor["method"]
    if method not in steps:
        raise SystemExit(f"the bench JSON has no workload of the anchor's method {method!r}; add "
                         f"{method}-800x600-300k to its --workloads")
    timings = anchor["timings"]
    if "train_cpu" not in timings:
        raise SystemExit("the anchor record has no timings.train_cpu (a run from before it was recorded); "
                         "choose a run of a later commit")
    train_anchor = code_factor * timings["train_cpu"]
    after = sum(timings.get(k, 0.0) for k in ("extract", "evaluate", "load"))
    return {m: {"step_ms": s, "train_s": train_anchor * s / steps[method], "total_s": train_anchor * s / steps[method]
                + after} for m, s in steps.items()}


def suite_run_costs(bench: dict, anchor: dict, code_factor: float, anchor_size: str, size: str,
                    pixels: float = 1.0, skip=()) -> dict[str, float]:
    """Per method of the bench at workload size ``size`` (``<m>-<size>``), but those in ``skip``: a run's estimated
    total seconds, ``F · T_a · s_m(size) / s_a(anchor_size) · pixels + E`` (module docstring)."""
    steps = {r["workload"]: r["step_ms"] for r in bench["result"]["results"]}
    anchor_workload = f"{anchor['method']}-{anchor_size}"
    if anchor_workload not in steps:
        raise SystemExit(f"the bench JSON has no workload {anchor_workload!r} (the anchor's method at --anchor-size); "
                         "add it to the bench's --workloads")
    timings = anchor["timings"]
    train_anchor = code_factor * timings["train_cpu"]
    after = sum(timings.get(k, 0.0) for k in ("extract", "evaluate", "load"))
    suffix = f"-{size}"
    costs = {name.removesuffix(suffix): train_anchor * step / steps[anchor_workload] * pixels + after
             for name, step in steps.items() if name.endswith(suffix) and name.removesuffix(suffix) not in skip}
    if not costs:
        raise SystemExit(f"the bench JSON has no workload of size {size!r} (<method>-{size})")
    return costs


def cluster_row(durations: list[float], cores: int, nodes: list[int]) -> dict:
    """Runs, core-hours, node-hours, the longest run (h) and the wall hours on each of ``nodes`` nodes of ``cores``
    one-thread slots, of runs lasting ``durations`` seconds."""
    return {"runs": len(durations), "core_h": sum(durations) / 3600, "node_h": sum(durations) / 3600 / cores,
            "longest_h": max(durations) / 3600,
            "wall_h": [list_schedule_makespan(durations, n * cores) / 3600 for n in nodes]}


def print_cluster_table(suites: dict, seeds: int, cores: int, nodes: list[int]) -> None:
    """The cluster table of ``suites`` ({name: (scenes, {method: seconds})}) and of all of them together."""
    print(f"| suite | runs | core-hours | node-hours ({cores} cores) | longest run (h) | "
          + " | ".join(f"wall on {n} nodes (h)" for n in nodes) + " |")
    print("|---|---|---|---|---|" + "---|" * len(nodes))
    every = []
    for name, (scenes, costs) in suites.items():
        durations = [seconds for seconds in costs.values() for _ in range(scenes * seeds)]
        every += durations
        _print_row(f"{name} ({scenes} scenes × {len(costs)} methods × {seeds} seeds)", cluster_row(durations, cores, nodes))
    if len(suites) > 1:
        _print_row("all", cluster_row(every, cores, nodes))


def _print_row(label: str, row: dict) -> None:
    print(f"| {label} | {row['runs']} | {row['core_h']:,.0f} | {row['node_h']:,.0f} | {row['longest_h']:.1f} | "
          + " | ".join(f"{h:.1f}" for h in row["wall_h"]) + " |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--bench", type=Path, required=True)
    parser.add_argument("--anchor", type=Path, required=True, help="a finished run's record.json")
    parser.add_argument("--anchor-code-factor", type=float, default=1.0)
    parser.add_argument("--scenes", type=int, default=7)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 3])
    parser.add_argument("--machines", type=int, nargs="+", default=[1, 16])
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--suite", nargs="+", action="append", metavar="NAME SCENES SIZE [PIXELS]",
                        help="a suite of the cluster table (module docstring); repeat for each")
    parser.add_argument("--anchor-size", default="800x600-300k", help="the bench workload size of the anchor run")
    parser.add_argument("--nodes", type=int, nargs="+", default=[4, 16, 64])
    parser.add_argument("--skip", nargs="+", default=[], help="methods left out of the cluster table")
    args = parser.parse_args()
    bench, anchor = json.loads(args.bench.read_text()), json.loads(args.anchor.read_text())
    if args.suite:
        suites = {}
        for name, scenes, size, *pixels in args.suite:
            suites[name] = (int(scenes), suite_run_costs(bench, anchor, args.anchor_code_factor, args.anchor_size, size,
                                                        float(pixels[0]) if pixels else 1.0, args.skip))
        for seeds in args.seeds:
            print_cluster_table(suites, seeds, args.cores, args.nodes)
        return
    costs = run_costs(bench, anchor, args.anchor_code_factor)
    print(f"anchor: {anchor['method']} run {anchor['run_id']}, train {anchor['timings']['train_cpu']:.0f} CPU-s, "
          f"code factor {args.anchor_code_factor:g}; bench: {bench['environment']['cpu']}, "
          f"{bench['result']['threads']} thread(s), commit {bench['environment']['git_commit'][:7]}")
    print("\n| method | bench step (ms) | one run: train (h) | one run: total (h) |")
    print("|---|---|---|---|")
    for m, c in costs.items():
        print(f"| {m} | {c['step_ms']:.0f} | {c['train_s'] / 3600:.1f} | {c['total_s'] / 3600:.1f} |")
    print(f"\nThe suite: {args.scenes} scenes × {len(costs)} methods, wall hours, one run per core at one thread "
          f"({args.cores} cores a machine):\n")
    print("| seeds | runs | " + " | ".join(f"{m} machine{'s' if m > 1 else ''}" for m in args.machines) + " |")
    print("|---|---|" + "---|" * len(args.machines))
    for seeds in args.seeds:
        runs = [c["total_s"] for c in costs.values() for _ in range(args.scenes * seeds)]
        spans = [list_schedule_makespan(runs, m * args.cores) / 3600 for m in args.machines]
        print(f"| {seeds} | {len(runs)} | " + " | ".join(f"{h:.1f}" for h in spans) + " |")


if __name__ == "__main__":
    main()
