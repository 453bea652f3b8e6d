"""One Ray node against two (or more) on the same sweep, back to back on this machine (experiments/cluster/README.md).

    python experiments/cluster/scaling.py [--nodes 1 2] [--cpus 1] [--work DIR]

For each node count, a fresh `gsbench.runs.ray_nodes.LocalCluster` of that many nodes of ``--cpus`` CPUs, then
``gsbench sweep experiments/cluster/scaling.yaml --executor ray --address <it> --threads 1`` into its own output
folder, timed from the sweep's start to its end (the cluster's start and stop are not counted). Prints each wall
time, its ratio to the first's and the load average before and after.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from gsbench.cli import main as gsbench
from gsbench.data.synthetic.make import make_scene
from gsbench.runs.ray_nodes import LocalCluster

SWEEP = Path(__file__).resolve().with_name("scaling.yaml")


def load() -> str:
    return " ".join(f"{value:.2f}" for value in os.getloadavg())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--nodes", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--cpus", type=int, default=1, help="CPUs of each node (one run at one thread on each)")
    parser.add_argument("--work", type=Path, default=None, help="a folder for the scene, clusters and outputs")
    args = parser.parse_args()
    work = (args.work or Path(tempfile.mkdtemp(prefix="gsbench-scaling-"))).resolve()
    make_scene("synthetic/spot", out=work / "scenes" / "spot-64x48", res=(64, 48))
    os.chdir(work)
    seconds = {}
    for nodes in args.nodes:
        with LocalCluster(work / f"cluster-{nodes}", nodes=nodes, cpus=args.cpus) as cluster:
            before = load()
            start = time.perf_counter()
            status = gsbench(["sweep", str(SWEEP), "--out", str(work / f"runs-{nodes}"), "--executor", "ray",
                              "--address", cluster.address, "--threads", "1"])
            seconds[nodes] = time.perf_counter() - start
            print(f"{nodes} node(s) of {args.cpus} CPU(s): {seconds[nodes]:.1f} s (exit {status}); load average "
                  f"before {before}, after {load()}", flush=True)
    first = args.nodes[0]
    for nodes, wall in seconds.items():
        print(f"{nodes} node(s): {wall:.1f} s, {seconds[first] / wall:.2f}x the speed of {first}")


if __name__ == "__main__":
    main()
