"""Concurrent and terminated sweeps (issue 65): two sweeps of one name writing one manifest at once (case 7), a sweep
stopped by SIGTERM or SIGHUP (case 9: in this process with a fake executor, and, marked slow, a real sweep in a
subprocess), a grid too large to expand (case 10c), and the report's failed-runs section above a killed run
(case 10e)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from pathlib import Path

import pytest

import gsbench.runs.executors
from gsbench.cli import main
from gsbench.errors import ConfigError, Interrupted
from gsbench.report.build import write_report
from gsbench.run_folder import RunFolder
from gsbench.runs.records import RunRecord
from gsbench.runs.runner import run_dir
from gsbench.runs.sweep import MAX_SWEEP_RUNS, Manifest, SweepRun, count_runs, expand, load_sweep, run_sweep
from tests.test_report import RUNS
from tests.test_sweep import THREE_SEEDS, fake_runs, write


# ---- case 7: one manifest, two writers ------------------------------------------------------------------------------

def test_two_sweeps_of_one_name_at_once_keep_each_others_runs(tmp_path, monkeypatch):
    """``--seeds 0`` and ``--seeds 1`` of one sweep started together on one ``--out``: each run waits until both sweeps
    have written their manifest, so every later write races the other sweep's (the last writer's runs alone were kept,
    or another's entry with its stale status)."""
    runs = expand(load_sweep(write(tmp_path, THREE_SEEDS)))
    calls = fake_runs(monkeypatch)
    both_started = threading.Barrier(2, timeout=30)
    fake = sys.modules["gsbench.runs.sweep"].run

    def run_after_both_started(cfg, echo=print):
        both_started.wait()
        fake(cfg, echo)

    monkeypatch.setattr("gsbench.runs.sweep.run", run_after_both_started)
    out = tmp_path / "runs"

    def sweep(seed):
        with ThreadPoolExecutor(1) as executor:
            return run_sweep([r for r in runs if r.config.seed == seed], executor, name="seeds", out=str(out),
                             echo=lambda *a: None)

    with ThreadPoolExecutor(2) as sweeps:
        summaries = list(sweeps.map(sweep, (0, 1)))
    assert [s.counts["ok"] for s in summaries] == [1, 1] and sorted(calls) == [0, 1]
    entries = json.loads((out / "sweeps" / "seeds.json").read_text())["runs"]
    assert sorted((e["seed"], e["status"]) for e in entries) == [(0, "ok"), (1, "ok")]
    assert not list((out / "sweeps").glob(".*.tmp"))


def test_many_writers_of_one_manifest_lose_no_entry(tmp_path):
    """Eight writers (threads, each with its own lock file descriptor, as separate processes have) set the statuses of
    their own runs over and over: the file ends with every writer's runs and their last statuses."""
    runs = expand(load_sweep(write(tmp_path, "base: {method: 3dgs, scene: synthetic/spot, preset: quick}\n"
                                             "grid: {seed: [0, 1, 2, 3, 4, 5, 6, 7], train.iterations: [10, 20]}")))
    path, out = tmp_path / "runs" / "sweeps" / "many.json", tmp_path / "runs"
    for r in runs:
        r.config.out = str(out)
    groups = [runs[2 * k:2 * k + 2] for k in range(8)]

    def writer(group: list[SweepRun]):
        manifest = Manifest(path, name="many", description="", file="", runs=group, out=out, finished=set())
        for status in ("failed", "cancelled", "ok") * 3:
            for r in group:
                manifest.set(r.run_id, status)

    threads = [threading.Thread(target=writer, args=(group,)) for group in groups]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=60)
    entries = json.loads(path.read_text())["runs"]
    assert sorted(e["run_id"] for e in entries) == sorted(r.run_id for r in runs)
    assert {e["status"] for e in entries} == {"ok"}


# ---- case 9: SIGTERM and SIGHUP -------------------------------------------------------------------------------------

class FirstRunThenSignal(Executor):
    """Runs the first task at once; the second "runs" (its future running, never done) and the others queue. After the
    last submit, ``signum`` arrives while the sweep waits; ``terminate_workers`` sends it once more (a scheduler's
    second notice, ignored), cancels the queue and ends the running task as a worker does on SIGTERM (`Interrupted`)."""

    def __init__(self, total: int, signum: int):
        self.total, self.signum, self.submitted, self.futures = total, signum, 0, []

    def submit(self, fn, /, *args):
        future = Future()
        self.submitted += 1
        if self.submitted == 1:
            future.set_result(fn(*args))
        else:
            self.futures.append(future)
            if self.submitted == 2:
                future.set_running_or_notify_cancel()
        if self.submitted == self.total:
            threading.Timer(0.2, os.kill, (os.getpid(), self.signum)).start()
        return future

    def terminate_workers(self):
        os.kill(os.getpid(), self.signum)
        running, *queued = self.futures
        running.set_exception(Interrupted("SIGTERM"))
        for future in queued:
            future.cancel()


@pytest.mark.parametrize("signum,status", [(signal.SIGTERM, 143), (signal.SIGHUP, 129)])
def test_sigterm_or_sighup_stops_the_sweeps_runs_says_which_and_exits_128_plus_the_signal(
        signum, status, tmp_path, monkeypatch, capsys):
    executor = FirstRunThenSignal(total=3, signum=signum)
    monkeypatch.setattr(gsbench.runs.executors, "make_executor", lambda *a, **k: executor)
    calls = fake_runs(monkeypatch)
    out = tmp_path / "runs"
    before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGHUP)}
    assert main(["sweep", str(write(tmp_path, THREE_SEEDS)), "--out", str(out)]) == status
    assert {s: signal.getsignal(s) for s in before} == before  # the sweep's handlers are gone again
    assert calls == [0]
    manifest = json.loads((out / "sweeps" / "sweep.json").read_text())
    assert [e["status"] for e in manifest["runs"]] == ["ok", "cancelled", "cancelled"]
    stdout = capsys.readouterr().out
    (line,) = [line for line in stdout.splitlines() if "stopped by" in line]
    name = signal.Signals(signum).name
    assert line.startswith(f"sweep sweep stopped by {name}: 1 running run stopped (3dgs on synthetic/spot, seed 1, "
                           f"run {manifest['runs'][1]['run_id']}), 1 not started; the same command resumes them")
    assert "sweep sweep interrupted: 1 ok, 0 skipped (finished earlier), 0 failed, 2 cancelled" in stdout


def test_a_signal_ignored_when_the_sweep_starts_stays_ignored(tmp_path, monkeypatch):
    """``nohup gsbench sweep ...`` ignores SIGHUP: the sweep must not take it back and stop at a closed terminal."""
    runs = expand(load_sweep(write(tmp_path, THREE_SEEDS)))[:1]
    seen = []

    def fake_run(cfg, echo=print):
        seen.append(signal.getsignal(signal.SIGHUP))
        RunRecord(run_id=cfg.run_id, method="3dgs", scene=cfg.scene, dataset="dtu", seed=cfg.seed,
                  status="ok").write(RunFolder(Path(cfg.out) / cfg.run_id).record)

    monkeypatch.setattr("gsbench.runs.sweep.run", fake_run)
    previous = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        with ThreadPoolExecutor(1) as executor:
            run_sweep(runs, executor, name="nohup", out=str(tmp_path / "runs"), echo=lambda *a: None)
    finally:
        signal.signal(signal.SIGHUP, previous)
    assert seen == [signal.SIG_IGN]


REAL_SWEEP = """
base:
  method: 3dgs
  scene: {scene}
  preset: quick
  train: {{iterations: 300, checkpoint_every: 20, log_every: 10}}
  mesh: {{voxel_size: 0.05, sdf_trunc: 0.2}}
  eval.evaluators: [mesh_stats]
  method.random_init_points: 1000
"""


def _wait_for(condition, seconds: float, what: str, process=None) -> None:
    deadline = time.perf_counter() + seconds
    while not condition():
        assert time.perf_counter() < deadline, f"no {what} after {seconds} s"
        assert process is None or process.poll() is None, f"the sweep ended (status {process.returncode}) before {what}"
        time.sleep(0.05)


def _process_gone(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] == "Z"  # exited, not reaped yet
    except FileNotFoundError:
        return True


@pytest.mark.slow  # two sweeps in subprocesses, each starting a worker: about 35 s on two idle cores, 70 s on busy ones
def test_a_real_sweep_stopped_by_sigterm_stops_its_worker_and_the_rerun_resumes_it(tiny_spot, tmp_path):
    """``gsbench sweep FILE --workers 1 --threads 1`` in the background, SIGTERM once its run has a checkpoint: the
    worker stops (no orphan), records the run interrupted and keeps the checkpoint; the sweep exits 143 with the line;
    the same command again resumes the run from the checkpoint (the metrics lines written before it are kept)."""
    path = tmp_path / "tiny.yaml"
    path.write_text(REAL_SWEEP.format(scene=tiny_spot))
    out = tmp_path / "runs"
    command = [sys.executable, "-m", "gsbench.cli", "sweep", str(path), "--out", str(out), "--workers", "1",
               "--threads", "1"]
    (sweep_run,) = expand(load_sweep(path))
    sweep_run.config.out = str(out)
    files = RunFolder(run_dir(sweep_run.config))
    log = (tmp_path / "first.log").open("w")
    sweep = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        _wait_for(files.checkpoint.is_file, 120, "checkpoint", sweep)
        worker = int(files.lock.read_text().split()[1])  # "pid N on HOST since ..."
        sweep.send_signal(signal.SIGTERM)
        assert sweep.wait(timeout=60) == 143, (tmp_path / "first.log").read_text()
        _wait_for(lambda: _process_gone(worker), 10, f"end of the worker {worker}")
    finally:
        if sweep.poll() is None:
            os.killpg(sweep.pid, signal.SIGKILL)
    output = (tmp_path / "first.log").read_text()
    assert f"stopped by SIGTERM: 1 running run stopped (3dgs on {tiny_spot}, seed 0, run {sweep_run.run_id})" in output
    assert RunRecord.read(files.record).status == "interrupted" and files.checkpoint.is_file()
    kept = files.metrics.read_text().splitlines()[0]

    again = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stdout + again.stderr
    assert "1 ok, 0 skipped (finished earlier), 0 failed, 0 cancelled" in again.stdout + again.stderr
    assert RunRecord.read(files.record).status == "ok"
    assert files.metrics.read_text().splitlines()[0] == kept  # resumed: a fresh start would have rewritten it


# ---- case 10c: a grid too large ------------------------------------------------------------------------------------

def test_the_run_count_comes_first_and_a_grid_too_large_is_refused_at_once(tmp_path, capsys):
    small = write(tmp_path, """
base: {method: 3dgs, scene: synthetic/spot, preset: quick}
variants: {a: {}, b: {train.iterations: 50}}
grid: {method.grad_threshold: [0.0002, 0.0004]}
zip: {train.log_every: [5, 10, 20]}
seeds: [0, 1]
""")
    assert count_runs(load_sweep(small)) == len(expand(load_sweep(small))) == 2 * 2 * 3 * 2
    assert main(["sweep", str(small), "--dry-run"]) == 0
    assert capsys.readouterr().out.startswith("# sweep sweep: 24 runs\n")

    values = "[" + ", ".join(str(k) for k in range(10)) + "]"
    huge = write(tmp_path, "base: {method: 3dgs, scene: synthetic/spot, preset: quick}\ngrid: {"
                 + ", ".join(f"train.k{k}: {values}" for k in range(6)) + "}\n")
    start = time.perf_counter()
    assert main(["sweep", str(huge), "--dry-run"]) == 2
    assert time.perf_counter() - start < 5
    err = capsys.readouterr().err
    assert f"1,000,000 runs, more than the {MAX_SWEEP_RUNS:,} a sweep may have" in err
    assert "fix: split the grid into several sweep files" in err
    with pytest.raises(ConfigError, match="1,000,000 runs"):
        expand(load_sweep(huge))


# ---- case 10e: the report above a killed run -----------------------------------------------------------------------

def test_the_failed_section_says_none_only_when_no_run_failed_or_is_unfinished(tmp_path):
    runs = tmp_path / "runs"
    shutil.copytree(RUNS, runs)
    for record in list(runs.rglob("record.json")):  # the fixture's failed run goes: no record that is not ok
        if json.loads(record.read_text())["status"] != "ok":
            shutil.rmtree(record.parent)
    write_report(runs, tmp_path / "clean", plots=False)
    section = (tmp_path / "clean" / "leaderboard.md").read_text().split("## Failed and unfinished runs\n")[1]
    assert section.split("## ")[0].strip() == "(none)"

    killed = runs / "dtu" / "scan24" / "3dgs" / "0123456789ab"
    killed.mkdir(parents=True)
    (killed / "config.yaml").write_text("method: {name: 3dgs}\n")
    (killed / "checkpoint.pt").write_bytes(b"")
    write_report(runs, tmp_path / "killed", plots=False)
    section = (tmp_path / "killed" / "leaderboard.md").read_text().split("## Failed and unfinished runs\n")[1]
    section = section.split("## ")[0]
    assert "(none)" not in section and "| dtu/scan24/3dgs/0123456789ab | no record: killed before it finished?" in section
