"""Executors (gsbench.runs.executors): the local process pool and Ray behind one concurrent.futures seam; tiny
real sweeps on each (two ok runs and a failing one; a second invocation resumes)."""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from concurrent.futures import CancelledError
from pathlib import Path

import pytest

import gsbench.runs.executors
from gsbench.errors import ConfigError, GsbenchError
from gsbench.runs.executors import LocalExecutor, RayExecutor, make_executor, threads_per_run


def test_workers_times_threads_must_fit_the_cores(monkeypatch):
    monkeypatch.setattr(gsbench.runs.executors, "cores", lambda: 4)
    with pytest.raises(ConfigError, match=r"--workers 3 × --threads 2 = 6 threads, more than the 4 cores.*<= 4"):
        make_executor("local", workers=3, threads=2)
    assert threads_per_run(None, 2) == 2 and threads_per_run(0, 3) == 1 and threads_per_run(3, 1) == 3


@pytest.mark.parametrize("kwargs,message", [
    ({"kind": "slurm", "workers": 1, "threads": 1}, "unknown executor 'slurm'; choose one of: local, ray"),
    ({"kind": "local", "workers": 0, "threads": 1}, "workers must be a positive integer, got 0"),
    ({"kind": "local", "workers": 1, "threads": 1, "address": "auto"}, "--address auto is for the ray executor"),
])
def test_bad_executor_settings_are_clear_errors(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        make_executor(kwargs.pop("kind"), **kwargs)


def test_ray_missing_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(GsbenchError, match=r'pip install "gsbench\[ray\]"'):
        make_executor("ray", workers=1, threads=1)


def test_local_workers_have_their_threads_and_leave_ctrl_c_to_the_sweep():
    with LocalExecutor(1, 1) as executor:
        assert executor.submit(os.getenv, "OMP_NUM_THREADS").result() == "1"
        assert executor.submit(signal.getsignal, signal.SIGINT).result() == signal.SIG_IGN
        assert executor.submit(signal.getsignal, signal.SIGHUP).result() == signal.SIG_IGN  # a closed terminal too


def test_local_executor_runs_each_task_in_a_fresh_process():
    # a run's peak memory is its process's ru_maxrss: a reused worker would report an earlier run's peak
    with LocalExecutor(1, 1) as executor:
        assert len({executor.submit(os.getpid).result() for _ in range(3)}) == 3


def test_terminate_workers_cancels_queued_tasks_and_stops_running_ones():
    executor = LocalExecutor(1, 1)
    running, queued = executor.submit(time.sleep, 60), executor.submit(time.sleep, 60)
    while not running.running():
        time.sleep(0.01)
    start = time.perf_counter()
    executor.terminate_workers()
    assert ending(running) == "BrokenProcessPool" and ending(queued) in ("cancelled", "BrokenProcessPool")
    assert time.perf_counter() - start < 30


def test_a_run_ending_after_shutdown_leaves_the_pool_working():
    """A worker that exits after its run (max_tasks_per_child=1) once the pool is shut down without waiting (a
    Ctrl-C as a run ends) must not kill the pool's manager thread: the other run still ends (it hung)."""
    executor = LocalExecutor(2, 1)
    short, long = executor.submit(time.sleep, 1), executor.submit(time.sleep, 3)
    while not (short.running() and long.running()):
        time.sleep(0.01)
    executor.shutdown(wait=False)
    assert short.result(timeout=30) is None and long.result(timeout=30) is None


def sleep_until_sigterm(seconds: float, ready: str) -> str:
    """A task that stops cleanly on SIGTERM, as a run does (it records "interrupted" and returns); it touches
    ``ready`` once its handler is in place."""
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    Path(ready).touch()
    stop.wait(seconds)
    return "stopped" if stop.is_set() else "slept"


def test_terminate_workers_ends_the_queued_task_when_the_running_one_stops_cleanly(tmp_path):
    """The running task returns on SIGTERM (no broken worker) and the next one is already in the pool's call
    queue, where nothing will run it: its future must still end (the sweep hung on it at a Ctrl-C)."""
    executor = LocalExecutor(1, 1)
    ready = tmp_path / "ready"
    running, queued = executor.submit(sleep_until_sigterm, 60, str(ready)), executor.submit(time.sleep, 60)
    deadline = time.perf_counter() + 60
    while not ready.exists() and time.perf_counter() < deadline:
        time.sleep(0.01)
    assert ready.exists()
    executor.terminate_workers()
    assert running.result(timeout=30) == "stopped"
    assert ending(queued) in ("cancelled", "BrokenProcessPool")


def ending(future) -> str:
    """How ``future`` ended: "cancelled" or its exception's type name (waits up to 30 s)."""
    try:
        return type(future.exception(timeout=30)).__name__
    except CancelledError:
        return "cancelled"


TINY_SWEEP = """
base:
  method: 3dgs
  scene: {scene}
  preset: quick
  train: {{iterations: 20, checkpoint_every: 0, log_every: 10}}
  mesh: {{voxel_size: 0.02, sdf_trunc: 0.08}}
  eval.evaluators: [dtu_chamfer]
zip:  # the third run fails once its scene is loaded: a scene without SfM points needs random init points
  seed: [0, 1, 0]
  method.random_init_points: [1000, 1000, 0]
"""


def sweep_twice(scene, tmp_path, capsys, *options):
    """``gsbench sweep`` of `TINY_SWEEP` with ``options``, twice: two ok runs and a failed one, then a resume."""
    import json

    from gsbench.cli import main
    from gsbench.runs.records import RunRecord
    from gsbench.runs.sweep import expand, load_sweep

    path = tmp_path / "tiny.yaml"
    path.write_text(TINY_SWEEP.format(scene=scene))
    out = tmp_path / "runs"
    workers = str(min(2, os.cpu_count() or 1))
    command = ["sweep", str(path), "--out", str(out), "--workers", workers, "--threads", "1", *options]
    assert main(command) == 1
    manifest = json.loads((out / "sweeps" / "tiny.json").read_text())
    assert [e["run_id"] for e in manifest["runs"]] == [r.run_id for r in expand(load_sweep(path))]
    assert [e["status"] for e in manifest["runs"]] == ["ok", "ok", "failed"]
    records = [RunRecord.read(out / e["dir"] / "record.json") for e in manifest["runs"]]
    assert [r.status for r in records] == ["ok", "ok", "failed"]
    assert all(r.environment["threads"] == 1 and r.metrics["chamfer"] > 0 for r in records[:2])
    assert "random_init_points must be > 0" in records[2].error_tail
    first = capsys.readouterr().out
    assert "2 ok, 0 skipped (finished earlier), 1 failed, 0 cancelled" in first and "random_init_points must be > 0" in first

    assert main(command) == 1
    assert "0 ok, 2 skipped (finished earlier), 1 failed, 0 cancelled" in capsys.readouterr().out
    assert [RunRecord.read(out / e["dir"] / "record.json").timings for e in manifest["runs"][:2]] == \
        [r.timings for r in records[:2]]


def test_local_executor_runs_two_tiny_runs_survives_a_failure_and_resumes(tiny_spot, tmp_path, capsys,
                                                                          restore_threads):
    sweep_twice(tiny_spot, tmp_path, capsys)


def test_a_process_that_ran_a_local_ray_cluster_is_refused_a_cluster_with_the_fix(monkeypatch):
    monkeypatch.setattr(RayExecutor, "local_sessions_in_process", 1)
    with pytest.raises(GsbenchError, match=r"has run a local Ray cluster before.*fix: run the sweep in a new process"):
        make_executor("ray", workers=1, threads=1, address="127.0.0.1:1")


@pytest.mark.ray
@pytest.mark.slow
def test_ray_executor_runs_two_tiny_runs_on_a_local_cluster(tiny_spot, tmp_path, capsys, restore_threads):
    sweep_twice(tiny_spot, tmp_path, capsys, "--executor", "ray")


@pytest.mark.ray
@pytest.mark.slow
def test_ray_runs_each_task_in_a_fresh_worker_at_the_drivers_priority(restore_threads):
    def pid_and_niceness() -> tuple[int, int]:  # local, so Ray pickles it by value (workers cannot import the test module)
        return os.getpid(), os.nice(0)

    environment = dict(os.environ)
    executor = make_executor("ray", workers=1, threads=1, echo=lambda *_: None)
    try:
        seen = [executor.submit(pid_and_niceness).result(timeout=120) for _ in range(3)]
        assert len({pid for pid, _ in seen}) == 3
        assert {niceness for _, niceness in seen} == {os.nice(0)}  # not Ray's default 15: runs are timed
    finally:
        executor.shutdown()
    assert dict(os.environ) == environment  # no RAY_AUTH_MODE=token left for the nodes and drivers started later
