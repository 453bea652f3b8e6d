"""Nothing is learnt late and nothing runs twice: configuration ranges are rejected before the scene is
read and before anything is written (``run``, ``config``, ``sweep --dry-run``); a run folder is locked
while a process works in it; SIGTERM leaves an ``interrupted`` (resumable) record."""

from __future__ import annotations

import os
import signal

import pytest

from gsbench.cli import main
from gsbench.config.checks import memory_check
from gsbench.errors import ConfigError
from gsbench.registry import METHODS
from gsbench.run_folder import RunFolder
from gsbench.runs.records import RunRecord
from gsbench.runs.run_lock import run_lock
from gsbench.runs.runner import resolve_run, run_dir
from gsbench.training.trainer import Trainer
from tests.test_runner import QUICK, gsbench_run

BAD = [("3dgs", "train.iterations=0", "train.iterations must be >= 1"),
       ("3dgs", "train.checkpoint_every=-1", "train.checkpoint_every must be >= 0"),
       ("ibgs", "method.knn_k=-3", "method.knn_k must be >= 1"),
       ("3dgs", "losses.nope=1", "unknown loss term 'nope'"),
       ("sugar", "method.regularizer=sdff", "regulariser mode"),
       ("2dgs", "mesh.extractor=tets", "supports mesh.extractor"),
       ("3dgs", "eval.dtu_culling=wide", "eval.dtu_culling must be one of 2dgs, gof, none"),
       ("3dgs", "losses.l1.weight=-1", "losses.l1.weight must be a finite number >= 0"),
       ("ibgs", "method.knn_k=100000", "this run needs about 134.1 GiB (kNN tables 134.1 GiB")]


@pytest.mark.parametrize("method, override, message", BAD)
def test_bad_values_fail_before_anything_is_read_or_written(method, override, message, tmp_path, capsys, monkeypatch):
    import gsbench.runs.runner as runner

    def no_scene(*_args, **_kwargs):
        raise AssertionError("the scene was made or read before the configuration was checked")

    monkeypatch.setattr(runner, "make_run_scene", no_scene)
    monkeypatch.setattr(runner, "load_run_scene", no_scene)
    out = tmp_path / "runs"
    assert main(["run", "--method", method, "--scene", "synthetic/spot", "--preset", "quick", "--out", str(out),
                 "--set", override]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()  # no run folder, no failed record
    assert main(["config", "--method", method, "--scene", "synthetic/spot", "--set", override]) == 2


def test_sweep_dry_run_checks_every_expanded_run(tmp_path, capsys):
    path = tmp_path / "k.yaml"
    path.write_text("base: {method: ibgs, scene: synthetic/spot, preset: quick}\ngrid:\n  method.knn_k: [5, 0]\n")
    assert main(["sweep", str(path), "--dry-run", "--out", str(tmp_path / "runs")]) == 2
    err = capsys.readouterr().err
    assert "method.knn_k=0" in err and "method.knn_k must be >= 1" in err
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("value", ["-1", "two"])
def test_threads_must_be_a_non_negative_integer(value, capsys):
    with pytest.raises(SystemExit):
        main(["--threads", value, "list"])
    assert "must be an integer >= 0" in capsys.readouterr().err


def test_a_second_process_in_a_locked_run_folder_exits_naming_the_holder(tiny_spot, tmp_path, capsys):
    cfg = resolve_run("3dgs", str(tiny_spot), preset="quick", overrides=QUICK)
    cfg.out = str(tmp_path / "runs")
    with run_lock(run_dir(cfg)):
        gsbench_run("3dgs", tiny_spot, tmp_path / "runs", expect=2)
    err = capsys.readouterr().err
    assert f"is in use by pid {os.getpid()}" in err and not (run_dir(cfg) / "record.json").exists()


def test_sigterm_records_an_interrupted_run_that_resumes(tiny_spot, tmp_path, monkeypatch):
    step = Trainer.train_step

    def terminate_at_45(self, t):
        if t == 45:
            os.kill(os.getpid(), signal.SIGTERM)
        return step(self, t)

    monkeypatch.setattr(Trainer, "train_step", terminate_at_45)
    before = signal.getsignal(signal.SIGTERM)  # SIG_DFL, or what an earlier test (ray.init) installed
    folder = gsbench_run("3dgs", tiny_spot, tmp_path / "runs", "eval.evaluators=[mesh_stats]", expect=143)
    record = RunRecord.read(folder / "record.json")
    assert record.status == "interrupted" and record.error_tail == "" and (folder / RunFolder.CHECKPOINT).is_file()
    assert signal.getsignal(signal.SIGTERM) is before  # the run's handler is gone again
    monkeypatch.undo()
    gsbench_run("3dgs", tiny_spot, tmp_path / "runs", "eval.evaluators=[mesh_stats]")
    assert RunRecord.read(folder / "record.json").status == "ok"


def test_report_names_damaged_records_on_the_console(tmp_path, capsys):
    import shutil
    from pathlib import Path

    runs = tmp_path / "runs"
    shutil.copytree(Path(__file__).parent / "fixtures" / "report" / "runs", runs)
    record = next(runs.rglob("record.json"))
    text = record.read_text()
    record.write_text(text[: len(text) // 2])  # truncated to half
    assert main(["report", str(runs), "--out", str(tmp_path / "r"), "--no-plots"]) == 0
    err = capsys.readouterr().err
    assert f"{record.relative_to(runs).as_posix()}: unreadable record skipped" in err
    only = tmp_path / "only"
    (only / record.relative_to(runs)).parent.mkdir(parents=True)
    (only / record.relative_to(runs)).write_text(text[: len(text) // 2])
    assert main(["report", str(only), "--out", str(tmp_path / "r2")]) == 2
    assert "no readable run record" in capsys.readouterr().err


def test_the_memory_check_names_what_dominates_and_passes_what_fits():
    cfg = resolve_run("ibgs", "synthetic/spot", preset="cpu")
    items = METHODS.get("ibgs").memory_estimate(cfg)
    assert set(items) == {"Gaussians", "render buffers", "kNN tables"}
    assert items["kNN tables"] == 72 * cfg.train.max_gaussians * cfg.method["knn_k"]
    memory_check(cfg, METHODS.get("ibgs").memory_estimate, available=2**30)  # ~0.2 GiB fits in 1 GiB
    with pytest.raises(ConfigError, match=r"needs about 0\.2 GiB \(Gaussians 0\.1 GiB.*but 0\.1 GiB is available"):
        memory_check(cfg, METHODS.get("ibgs").memory_estimate, available=2**30 // 10)
    tets = resolve_run("gof", "synthetic/spot-tnt", preset="cpu")
    assert tets.mesh.extractor == "tets" and "tetrahedra" in METHODS.get("gof").memory_estimate(tets)
