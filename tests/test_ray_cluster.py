"""A real multi-node Ray cluster (gsbench.runs.ray_nodes.LocalCluster: `ray start --head` and `ray start --address`
on this machine, each node with its own temp folder, run folder and scene cache) runs a tiny sweep with no shared
disk: its records equal a local sweep's, metric for metric; each task wrote only under its node's folder; a built-in
scene generated on each node is the driver's, file for file. Each Ray driver is a process of its own, as the gsbench
command is (a process that started a local Ray cluster before cannot connect to one: `RayExecutor`)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import pytest

from gsbench.cli import main
from gsbench.data.synthetic.make import ensure_scene
from gsbench.runs.ray_nodes import LocalCluster
from gsbench.runs.records import RunRecord
from gsbench.runs.scene_shipping import SHIPPED, folder_hash

pytestmark = [pytest.mark.slow, pytest.mark.ray]

SWEEP = """
base:
  method: 3dgs
  scene: scenes/spot-64x48
  preset: quick
  train: {iterations: 20, checkpoint_every: 0, log_every: 10}
  mesh: {voxel_size: 0.02, sdf_trunc: 0.08}
  eval.evaluators: [mesh_stats, silhouette]
  method.random_init_points: 1000
seeds: [0, 1]
"""
# Asked of the cluster by a driver process of its own: the node index of each run id's node, and the content hash of
# synthetic/spot generated on each node (argv: address, {run_id: node_id}, node count).
PROBE = """
import json, sys
import ray
from gsbench.data.synthetic.make import ensure_scene
from gsbench.runs.ray_nodes import node_index, node_resource
from gsbench.runs.scene_shipping import folder_hash

def generated_scene_hash(name):
    return folder_hash(ensure_scene(name))

ray.init(address=sys.argv[1], log_to_driver=False)
by_node = {run_id: node_index(ray, node_id) for run_id, node_id in json.loads(sys.argv[2]).items()}
generate = ray.remote(num_cpus=1)(generated_scene_hash)
hashes = ray.get([generate.options(resources={node_resource(i): 1}).remote("synthetic/spot")
                  for i in range(int(sys.argv[3]))])
ray.shutdown()
print(json.dumps({"by_node": by_node, "hashes": hashes}))
"""
# What a run's record holds that depends on where and when it ran, not on what it computed.
WHERE_AND_WHEN = ("environment", "timings", "peak_rss_bytes", "it_per_s")


def records(out) -> dict:
    manifest = json.loads((out / "sweeps" / "tiny.json").read_text())
    return {entry["run_id"]: RunRecord.read(out / entry["dir"] / "record.json").to_dict() for entry in manifest["runs"]}


def without(record: dict, out) -> dict:
    """``record`` without `WHERE_AND_WHEN` and its points' times (``*_seconds``), its output folder written as OUT."""
    kept = {key: value for key, value in record.items() if key not in WHERE_AND_WHEN}
    kept["points"] = [{key: value for key, value in point.items() if not key.endswith("_seconds")}
                      for point in record["points"]]
    return json.loads(json.dumps(kept).replace(str(out.resolve()), "OUT"))


def driver(*args: str) -> str:
    """``python *args`` in a new process (the test's folder, its environment): its stdout; its output on failure."""
    done = subprocess.run([sys.executable, *args], capture_output=True, text=True, env=os.environ.copy(), check=False)
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-4000:]
    return done.stdout


def test_a_two_node_cluster_sweeps_as_a_local_sweep_with_no_shared_disk(tiny_spot, tmp_path, monkeypatch,
                                                                        restore_threads):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("GSBENCH_DATA", str(tmp_path / "driver-scenes"))
    shutil.copytree(tiny_spot, tmp_path / "scenes" / "spot-64x48")  # a user's scene, given relative: shipped
    (tmp_path / "tiny.yaml").write_text(SWEEP)
    local, remote = tmp_path / "local", tmp_path / "ray"
    assert main(["sweep", "tiny.yaml", "--out", str(local), "--workers", "1", "--threads", "1"]) == 0

    with LocalCluster(tmp_path / "cluster", nodes=2, cpus=1) as cluster:
        driver("-m", "gsbench.cli", "sweep", "tiny.yaml", "--out", str(remote), "--executor", "ray",
               "--address", cluster.address, "--threads", "1")
        node_ids = {run_id: record["environment"]["ray"]["node_id"] for run_id, record in records(remote).items()}
        probe = json.loads(driver("-c", PROBE, cluster.address, json.dumps(node_ids), "2").splitlines()[-1])
    by_node, hashes = probe["by_node"], probe["hashes"]

    ray_records, local_records = records(remote), records(local)
    assert set(ray_records) == set(local_records) and len(ray_records) == 2
    for run_id, record in ray_records.items():
        assert record["status"] == "ok" and record["metrics"] and record["mesh"]["sha256"]
        assert without(record, remote) == without(local_records[run_id], local)
        assert record["environment"]["ray"]["attempts"] == 1
    assert sorted(by_node.values()) == [0, 1]  # a run on each node

    shipped = folder_hash(tmp_path / "scenes" / "spot-64x48")
    for index in range(2):
        node = cluster.folder(index)
        mine = {run_id for run_id, where in by_node.items() if where == index}
        ran_here = {path.parent.name for path in cluster.run_folder(index).rglob("record.json")}
        assert ran_here == mine  # each task ran in its own node's folder
        assert (cluster.scene_cache(index) / SHIPPED / shipped / "scenes" / "spot-64x48").is_dir()
        assert not any(node.rglob("sweeps"))  # the sweep's manifest is the driver's alone
    assert hashes == [folder_hash(ensure_scene("synthetic/spot"))] * 2  # a built-in scene generated alike on each node
