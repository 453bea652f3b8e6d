"""A Ray cluster of several nodes on this one machine (`LocalCluster`), as a real cluster's nodes share no disk.

Node 0 is started with ``ray start --head``, the others with ``ray start --address`` to it; each with ``--block``
in its own process session (so that stopping it ends every process it started, and nothing else), its own
``--temp-dir``, its own run folder (``GSBENCH_NODE_RUNS``) and its own scene cache (``GSBENCH_DATA``), and a custom
resource ``node-<i>`` (`node_index` tells which node a Ray node id is). Its nodes ask no authentication token
(``RAY_AUTH_MODE=disabled``, as a driver connects by default): a test cluster of one machine. Its workers run at
the driver's priority (``RAY_worker_niceness=0``), as the Ray executor's own local cluster's do. tests/test_ray_cluster.py and
experiments/cluster/scaling.py sweep on it (docs/cluster.md §5).
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from gsbench.errors import GsbenchError
from gsbench.runs.executors import import_ray
from gsbench.switches import DATA, NODE_RUNS

START_SECONDS = 180  # the most a node may take to join the cluster
STOP_SECONDS = 30  # a node's processes are killed when they have not ended this long after SIGTERM
RAY = [sys.executable, "-m", "ray.scripts.scripts"]  # this interpreter's Ray: its workers run this gsbench


def free_port(ip: str) -> int:
    with socket.socket() as probe:
        probe.bind((ip, 0))
        return probe.getsockname()[1]


def node_resource(index: int) -> str:
    return f"node-{index}"


class LocalCluster:
    """``nodes`` Ray nodes of ``cpus`` CPUs each under ``root`` (``root/node-<i>/``: ``runs/`` its run folder,
    ``scenes/`` its scene cache, ``ray-start.log``; its Ray temp folder is a short one in the system's temp folder,
    as Ray's socket paths must stay under 108 bytes, removed at stop); a context manager: started on entry, stopped
    on exit. ``address``: what ``ray.init`` / ``gsbench sweep --address`` connect to."""

    def __init__(self, root, nodes: int = 2, cpus: int = 1):
        if nodes < 1 or cpus < 1:
            raise GsbenchError(f"a local cluster needs at least one node of one CPU, got {nodes} of {cpus}")
        self.root, self.nodes, self.cpus = Path(root).resolve(), nodes, cpus
        self.ip = import_ray().util.get_node_ip_address()  # the address Ray gives this machine's nodes
        self.address = f"{self.ip}:{free_port(self.ip)}"
        self._processes: list[subprocess.Popen] = []
        self._temp_dirs: list[str] = []

    def folder(self, index: int) -> Path:
        return self.root / node_resource(index)

    def run_folder(self, index: int) -> Path:
        """Node ``index``'s run folder (its ``GSBENCH_NODE_RUNS``)."""
        return self.folder(index) / "runs"

    def scene_cache(self, index: int) -> Path:
        """Node ``index``'s scene cache (its ``GSBENCH_DATA``)."""
        return self.folder(index) / "scenes"

    def __enter__(self) -> "LocalCluster":
        self.start()
        return self

    def __exit__(self, *_exc) -> None:
        self.stop()

    def start(self) -> None:
        """Start the head, then the other nodes, and wait until all have joined (`START_SECONDS`)."""
        try:
            for index in range(self.nodes):
                self._processes.append(self._start_node(index))
                if index == 0:
                    self._wait_for_nodes(1)
            self._wait_for_nodes(self.nodes)
        except BaseException:
            self.stop()
            raise

    def _start_node(self, index: int) -> subprocess.Popen:
        folder = self.folder(index)
        for path in (self.run_folder(index), self.scene_cache(index)):
            path.mkdir(parents=True, exist_ok=True)
        self._temp_dirs.append(tempfile.mkdtemp(prefix=f"gsbench-{node_resource(index)}-"))
        port = self.address.rsplit(":", 1)[1]
        role = ["--head", f"--port={port}", "--include-dashboard=false"] if index == 0 else [f"--address={self.address}"]
        command = [*RAY, "start", *role, "--block", f"--node-ip-address={self.ip}", f"--num-cpus={self.cpus}", "--num-gpus=0",
                   f"--temp-dir={self._temp_dirs[-1]}", f'--resources={{"{node_resource(index)}": 1}}',
                   "--disable-usage-stats"]
        env = {**os.environ, NODE_RUNS.name: str(self.run_folder(index)), DATA.name: str(self.scene_cache(index)),
               "RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_MODE": "disabled", "RAY_worker_niceness": "0"}
        log = open(folder / "ray-start.log", "wb")  # noqa: SIM115  (the node writes it until it stops)
        return subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)

    def _alive_nodes(self) -> int:
        """How many nodes ``ray status`` lists (by their ``node-<i>`` resources)."""
        status = subprocess.run([*RAY, "status", f"--address={self.address}"], capture_output=True, text=True,
                                timeout=60, check=False)
        if status.returncode != 0:
            return 0
        return sum(bool(re.search(rf"\b{node_resource(index)}\b", status.stdout)) for index in range(self.nodes))

    def _wait_for_nodes(self, count: int) -> None:
        deadline = time.monotonic() + START_SECONDS
        while time.monotonic() < deadline:
            dead = [p for p in self._processes if p.poll() is not None]
            if dead:
                raise GsbenchError(f"a Ray node of the local cluster exited at start; see {self.root}/node-*/"
                                   "ray-start.log")
            if self._alive_nodes() >= count:
                return
            time.sleep(1)
        raise GsbenchError(f"{count} Ray node(s) did not join in {START_SECONDS} s; see {self.root}/node-*/"
                           "ray-start.log")

    def stop(self) -> None:
        """SIGTERM to each node's process session, the workers first, then SIGKILL to what is left after
        `STOP_SECONDS`."""
        for process in reversed(self._processes):
            _signal_session(process, signal.SIGTERM)
        deadline = time.monotonic() + STOP_SECONDS
        for process in reversed(self._processes):
            try:
                process.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
            _signal_session(process, signal.SIGKILL)
        self._processes.clear()
        for folder in self._temp_dirs:
            shutil.rmtree(folder, ignore_errors=True)
        self._temp_dirs.clear()


def _signal_session(process: subprocess.Popen, signum: int) -> None:
    """``signum`` to every process of ``process``'s session (its process group), when any is left."""
    try:
        os.killpg(process.pid, signum)
    except ProcessLookupError:
        pass


def node_index(ray, node_id: str) -> int:
    """The local cluster's index of the Ray node ``node_id`` (its ``node-<i>`` resource), from ``ray.nodes()``."""
    for node in ray.nodes():
        if node["NodeID"] == node_id:
            return next(int(name.split("-")[1]) for name in node["Resources"] if name.startswith("node-"))
    raise GsbenchError(f"Ray node {node_id} is not in the cluster")
