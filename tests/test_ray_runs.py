"""Ray runs with no shared disk (gsbench.runs.node_runs, gsbench.runs.scene_shipping, the Ray executor): a run's
outputs come back through Ray and land in --out, the size caps, scene shipping by content hash, retries recorded, a
restarted driver skipping finished runs, a second driver refused, the sweep's ETA. Fast: the run functions are
stand-ins that write a run folder's files, on one local Ray cluster for the module."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest

import gsbench.runs.executors as executors
import gsbench.runs.node_runs as node_runs
import gsbench.runs.scene_shipping as scene_shipping
from gsbench.config.files import config_root, load_yaml, paper_methods
from gsbench.errors import ConfigError, GsbenchError
from gsbench.run_folder import RunFolder
from gsbench.runs.executors import make_executor
from gsbench.runs.node_runs import NodeResult, collect_outputs, land_outputs, run_on_node
from gsbench.runs.run_lock import RunLockedError, run_lock
from gsbench.runs.runner import resolve_run, run_dir
from gsbench.runs.scene_shipping import SceneShipper, SceneTicket, check_scene_hash, folder_hash, scene_on_node
from gsbench.runs.sweep import RunOutcome, SweepRun, count_runs, eta_seconds, load_sweep, run_sweep

def tiny_config(seed: int = 0, out: str = "runs"):
    cfg = resolve_run("3dgs", "synthetic/spot", preset="quick", seed=seed)
    cfg.out = out
    return cfg


def fake_run(calls: str, crash_first: str = ""):
    """A stand-in for `gsbench.runs.sweep.run_one`, pickled by value (Ray workers cannot import this test module):
    it appends its run id to ``calls``, writes a run folder's files (its out path inside the texts) and returns
    an ok outcome; with ``crash_first`` (a file), the first call anywhere kills its worker, as a node dying would."""

    def run(cfg):
        if crash_first and not os.path.exists(crash_first):
            Path(crash_first).touch()
            os._exit(1)
        with open(calls, "a") as fh:
            fh.write(cfg.run_id + "\n")
        files = RunFolder(run_dir(cfg))
        files.path.mkdir(parents=True, exist_ok=True)
        files.config.write_text(f"out: {cfg.out}\n")
        files.mesh.write_bytes(b"ply mesh bytes")
        files.checkpoint.write_bytes(b"a large checkpoint")
        files.lock.write_text("pid 1")
        files.point_eval(5).parent.mkdir(parents=True)
        files.point_eval(5).write_text(json.dumps({"mesh": str(files.point_mesh(5))}))
        record = {"run_id": cfg.run_id, "method": "3dgs", "scene": cfg.scene, "dataset": "dtu", "seed": cfg.seed,
                  "config": cfg.to_dict(), "status": "ok", "environment": {"host": "node"},
                  "mesh": {"path": str(files.mesh)}}
        files.record.write_text(json.dumps(record))
        return RunOutcome(cfg.run_id, "ok", 1.0)

    return run


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """One local Ray cluster of 1 CPU whose node runs in its own folder (``node``) with its own scene cache."""
    base = tmp_path_factory.mktemp("ray")
    before = os.environ.get("GSBENCH_NODE_RUNS")
    os.environ["GSBENCH_NODE_RUNS"] = str(base / "node")  # the workers inherit it when Ray starts
    executor = make_executor("ray", workers=1, threads=1, echo=lambda *_: None)
    try:
        yield SimpleNamespace(executor=executor, node=base / "node")
    finally:
        executor.shutdown()
        os.environ.pop("GSBENCH_NODE_RUNS")
        if before is not None:
            os.environ["GSBENCH_NODE_RUNS"] = before


def unchecked(scene: str) -> SceneTicket:
    return SceneTicket(scene, "shared", cwd=os.getcwd())


@pytest.mark.ray
def test_outputs_arrive_at_the_driver_when_the_nodes_folder_is_deleted_after_the_task(cluster, tmp_path):
    ray = cluster.executor.ray
    cfg = tiny_config(out=str(tmp_path / "out"))
    ref = ray.remote(num_cpus=1)(run_on_node).remote(fake_run(str(tmp_path / "calls")), cfg, unchecked(cfg.scene), 1)
    ray.wait([ref])
    node_folder = run_dir(tiny_config(out=str(cluster.node)))
    assert (node_folder / "record.json").is_file()  # the task ran in the node's folder
    shutil.rmtree(cluster.node)
    assert land_outputs(ray.get(ref), cfg, None) == RunOutcome(cfg.run_id, "ok", 1.0)
    files = RunFolder(run_dir(cfg))
    assert files.mesh.read_bytes() == b"ply mesh bytes"
    assert files.config.read_text() == f"out: {Path(cfg.out).resolve()}\n"  # the node's folder named as the driver's
    assert json.loads(files.point_eval(5).read_text())["mesh"] == str(files.point_mesh(5))
    record = json.loads(files.record.read_text())
    assert record["mesh"]["path"] == str(files.mesh) and record["config"]["out"] == str(Path(cfg.out).resolve())
    assert record["environment"]["ray"]["attempts"] == 1 and record["environment"]["ray"]["retried"] is False
    assert not files.checkpoint.exists() and not files.lock.exists()  # checkpoints stay on the node


@pytest.mark.ray
def test_a_run_through_the_executor_lands_in_out_and_a_retried_one_says_so(cluster, tmp_path):
    cfg = tiny_config(seed=1, out=str(tmp_path / "out"))
    future = cluster.executor.submit(fake_run(str(tmp_path / "calls"), crash_first=str(tmp_path / "crashed")), cfg)
    assert future.result(timeout=300).status == "ok"
    ray_env = json.loads(RunFolder(run_dir(cfg)).record.read_text())["environment"]["ray"]
    assert ray_env["attempts"] == 2 and ray_env["retried"] is True and ray_env["node_id"]
    assert (tmp_path / "crashed").exists()


@pytest.mark.ray
def test_a_run_whose_worker_always_dies_is_sent_at_most_the_retries_again(cluster, tmp_path, monkeypatch):
    starts = tmp_path / "starts"

    def always_crash(cfg):  # local, so Ray pickles it by value; each start leaves a line, then kills its worker
        with open(starts, "a") as fh:
            fh.write(cfg.run_id + "\n")
        os._exit(1)

    monkeypatch.setattr(executors, "NODE_DEATH_RETRIES", 1)
    future = cluster.executor.submit(always_crash, tiny_config(seed=2, out=str(tmp_path / "out")))
    with pytest.raises(cluster.executor.ray.exceptions.WorkerCrashedError):
        future.result(timeout=300)
    assert len(starts.read_text().splitlines()) == 2  # the first start and one retry


def test_outputs_above_the_cap_are_a_clear_error(tmp_path, monkeypatch):
    (tmp_path / "mesh.ply").write_bytes(b"x" * 100)
    (tmp_path / "checkpoint.pt").write_bytes(b"x" * 1000)  # stays on the node: not counted
    monkeypatch.setattr(node_runs, "OUTPUTS_CAP_BYTES", 99)
    with pytest.raises(node_runs.OutputsTooLarge, match=r"more than the .* GiB a Ray task sends back.*fix: "):
        collect_outputs(tmp_path)
    monkeypatch.setattr(node_runs, "OUTPUTS_CAP_BYTES", 100)
    assert list(collect_outputs(tmp_path)) == ["mesh.ply"]


def make_scene_folder(root: Path) -> Path:
    folder = root / "data" / "scan1"
    (folder / "images").mkdir(parents=True)
    (folder / "images" / "0000.png").write_bytes(b"pixels")
    (folder / "cameras.npz").write_bytes(b"cameras")
    return folder


def test_a_relative_scene_is_shipped_once_by_hash_and_unpacked_once_per_node(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    folder = make_scene_folder(tmp_path)
    puts, gets = [], []
    shipper = SceneShipper(lambda data: puts.append(data) or f"ref{len(puts)}")
    ticket = shipper.ticket("data/scan1")
    assert shipper.ticket("data/scan1") is ticket and len(puts) == 1  # put once for every run of the scene
    assert ticket.kind == "shipped" and ticket.content_hash == folder_hash(folder) and ticket.payload == ["ref1"]

    monkeypatch.setenv("GSBENCH_DATA", str(tmp_path / "node-cache"))
    for _ in range(2):
        with scene_on_node(ticket, lambda ref: gets.append(ref) or puts[0]) as found:
            assert found == ticket.content_hash
            assert Path("data/scan1/images/0000.png").read_bytes() == b"pixels"  # the run reads it at its own path
            assert Path.cwd() == tmp_path / "node-cache" / "shipped" / ticket.content_hash
    assert gets == ["ref1"] and Path.cwd() == tmp_path  # fetched once on this node


def test_a_scene_too_large_to_ship_names_the_shared_option(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    make_scene_folder(tmp_path)
    monkeypatch.setattr(scene_shipping, "SHIP_CAP_BYTES", 5)
    with pytest.raises(ConfigError, match=r"data/scan1: .* GiB, more than .* set executor.scene_paths: shared"):
        SceneShipper(lambda data: data).ticket("data/scan1")
    shared = SceneShipper(lambda data: data, "shared").ticket("data/scan1")
    assert shared.kind == "shared" and shared.content_hash is None and shared.cwd == str(tmp_path)
    with pytest.raises(ConfigError, match="executor.scene_paths must be one of ship, shared"):
        SceneShipper(lambda data: data, "nfs")


@pytest.mark.ray
def test_a_run_whose_scene_is_too_large_to_ship_fails_unsent(cluster, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    make_scene_folder(tmp_path)
    monkeypatch.setattr(scene_shipping, "SHIP_CAP_BYTES", 5)
    cfg = tiny_config(out=str(tmp_path / "out"))
    cfg.scene = "data/scan1"
    future = cluster.executor.submit(fake_run(str(tmp_path / "calls")), cfg)
    with pytest.raises(ConfigError, match="set executor.scene_paths: shared"):
        future.result(timeout=60)
    assert not (tmp_path / "calls").exists()  # never sent to a node


def test_a_scene_read_differently_on_a_node_is_refused_before_anything_is_written(tmp_path):
    check_scene_hash("synthetic/spot", "a" * 64, "a" * 64, "n" * 40)
    with pytest.raises(GsbenchError, match=r"synthetic/spot: node nnnnnnnnnnnn read other files than the driver's"):
        check_scene_hash("synthetic/spot", "a" * 64, "b" * 64, "n" * 40)
    cfg = tiny_config(out=str(tmp_path / "out"))
    result = NodeResult("ran", {"record.json": b"{}"}, "/node", "n" * 40, 1, "b" * 64)
    with pytest.raises(GsbenchError, match="read other files"):
        land_outputs(result, cfg, "a" * 64)
    assert not run_dir(cfg).exists()


def test_the_folder_hash_sees_a_changed_byte_and_a_renamed_file(tmp_path):
    folder = make_scene_folder(tmp_path)
    before = folder_hash(folder)
    (folder / "cameras.npz").write_bytes(b"cameraz")
    changed = folder_hash(folder)
    (folder / "cameras.npz").rename(folder / "cameras2.npz")
    assert len({before, changed, folder_hash(folder)}) == 3


@pytest.mark.ray
def test_a_restarted_driver_skips_the_finished_runs_and_submits_the_rest(cluster, tmp_path, monkeypatch):
    import gsbench.runs.sweep as sweep

    calls = tmp_path / "calls"
    monkeypatch.setattr(sweep, "run_one", fake_run(str(calls)))
    first, second = (SweepRun("base", tiny_config(seed=seed)) for seed in (10, 11))
    out = str(tmp_path / "out")
    quiet = {"out": out, "other_code": "keep", "echo": lambda *_: None}
    run_sweep([first], cluster.executor, name="restart", **quiet)  # the driver that was killed after one run
    assert calls.read_text().split() == [first.run_id]
    summary = run_sweep([first, second], cluster.executor, name="restart", **quiet)
    assert summary.counts["skipped"] == 1 and summary.counts["ok"] == 1
    assert calls.read_text().split() == [first.run_id, second.run_id]


def test_a_second_driver_on_one_out_is_refused(tmp_path):
    out = tmp_path / "out"
    with run_lock(out):  # the first driver, sweeping into out
        with pytest.raises(RunLockedError, match=f"{out} is in use by pid {os.getpid()}"):
            run_sweep([SweepRun("base", tiny_config())], SimpleNamespace(runs_elsewhere=True), out=str(out),
                      echo=lambda *_: None)
    assert not (out / "sweeps").exists()  # refused before its manifest


def test_the_eta_is_the_mean_run_time_over_the_waves_left():
    assert eta_seconds([], 5, 2) is None
    assert eta_seconds([10.0, 30.0], 5, 2) == 60.0  # 20 s a run, 3 waves of 2 slots
    assert eta_seconds([10.0], 4, 4) == 10.0


@pytest.mark.parametrize("file,dataset,runs", [("dtu_papers.yaml", "dtu", 450), ("tnt_papers.yaml", "tnt", 180)])
def test_the_cluster_sweeps_are_the_papers_protocol(file, dataset, runs):
    """configs/cluster/: every method of the benchmark at the papers' preset, three seeds, on the scenes of the
    papers' own tables (2DGS's, configs/methods/2dgs.yaml), on a Ray cluster."""
    sweep = load_sweep(config_root() / "cluster" / file)
    assert tuple(sweep["grid"]["method"]) == paper_methods() and sweep["base"]["preset"] == "paper"
    assert sweep["seeds"] == [0, 1, 2] and count_runs(sweep) == runs
    papers = load_yaml(config_root() / "methods" / "2dgs.yaml")["reported"][dataset]["scenes"]
    assert [Path(scene).name for scene in sweep["scenes"]] == list(papers)
    assert sweep["executor"]["kind"] == "ray" and sweep["executor"]["address"] == "auto"
