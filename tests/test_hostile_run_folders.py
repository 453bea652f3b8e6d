"""Hostile run folders (issue 65): paths below ``--out`` that cannot be written, a disk that fills during a run, an
edited run folder, a resumed run, a finished run run again. Each is one line naming the path and the fix, before
the work, or correct behaviour; nothing is lost and a rerun resumes to the uninterrupted result."""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import tempfile

import pytest
import torch
import yaml

import gsbench.atomic as atomic
from gsbench.atomic import DiskFullError, atomic_path
from gsbench.cli import main
from gsbench.run_folder import RunFolder
from gsbench.runs.records import RunRecord, check_folder_identity
from gsbench.runs.runner import resolve_run, run_dir
from gsbench.training.trainer import load_checkpoint

TINY = ["data.downscale=1", "method.random_init_points=500", "train.iterations=20", "train.checkpoint_every=10",
        "train.log_every=5", "mesh.voxel_size=0.02", "mesh.sdf_trunc=0.08", "eval.evaluators=[mesh_stats]"]


def run_args(scene, out, *sets):
    return ["--threads", "1", "run", "--method", "3dgs", "--scene", str(scene), "--preset", "quick", "--out", str(out),
            *[arg for s in (*TINY, *sets) for arg in ("--set", s)]]


def folder_of(scene, out, *sets):
    cfg = resolve_run("3dgs", str(scene), preset="quick", overrides=[*TINY, *sets])
    cfg.out = str(out)
    return run_dir(cfg)


def gsbench(args) -> tuple[int, str]:
    """(exit status, stderr) of the command line ``args``."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        status = main(args)
    return status, err.getvalue()


def error_line(err: str) -> str:
    """The one error line of ``err``, which holds no traceback."""
    errors = [line for line in err.splitlines() if line.startswith("gsbench: error:")]
    assert len(errors) == 1 and "Traceback" not in err, err
    return errors[0]


@pytest.fixture(scope="module")
def finished(tiny_spot, tmp_path_factory):
    """A finished quick run, trained straight through: its folder."""
    out = tmp_path_factory.mktemp("finished") / "runs"
    assert gsbench(run_args(tiny_spot, out))[0] == 0
    return folder_of(tiny_spot, out)


# ---- case 1: every path the run writes below --out, checked before the work ------------------------------------

def _blocked(kind: str, out, monkeypatch) -> str:
    """Puts ``kind`` of obstacle below ``out``; returns what the error must say."""
    folder = folder_of("synthetic/spot", out)
    dataset = out / "dtu"
    if kind == "file where a folder goes":
        dataset.mkdir(parents=True)
        (dataset / "spot").write_text("")
        return f"{folder}: cannot write there: {dataset / 'spot'} is a file, not a folder; fix: move that file away, or"
    if kind == "read-only folder deeper":
        (dataset / "spot").mkdir(parents=True)
        access = os.access
        monkeypatch.setattr(atomic.os, "access", lambda path, mode: os.fspath(path) != os.fspath(dataset / "spot")
                            and access(path, mode))  # as on a read-only file system (root cannot write there either)
        return f"{folder}: cannot write there: {dataset / 'spot'} is not writable (read-only folder or file system)"
    if kind == "symlink loop as --out":
        out.symlink_to(out)
        return f"{folder}: cannot write there: {out} is a symbolic link loop; fix: point it at a folder or remove it"
    if kind == "link to nowhere":
        out.mkdir()
        dataset.symlink_to(out / "gone")
        return f"{dataset} is a symbolic link to {out / 'gone'}, which does not exist; fix: create that folder, or"
    if kind == "folder where a file goes":
        (folder / RunFolder.RECORD).mkdir(parents=True)
        return (f"{folder / RunFolder.RECORD}: cannot write there: it is a folder, where a file will be written; fix: "
                "move it away, or")
    assert kind == "read-only file"
    folder.mkdir(parents=True)
    (folder / RunFolder.METRICS).write_text("")
    access = os.access
    monkeypatch.setattr(atomic.os, "access", lambda path, mode: not os.fspath(path).endswith(RunFolder.METRICS)
                        and access(path, mode))
    return (f"{folder / RunFolder.METRICS}: cannot write there: the file is read-only; fix: make it writable "
            f"(chmod u+w {folder / RunFolder.METRICS}), or")


@pytest.mark.parametrize("kind", ["file where a folder goes", "read-only folder deeper", "symlink loop as --out",
                                  "link to nowhere", "folder where a file goes", "read-only file"])
def test_a_path_below_out_that_cannot_be_written_is_one_line_before_any_work(kind, tmp_path, monkeypatch):
    import gsbench.runs.runner as runner

    monkeypatch.setattr(runner, "make_run_scene", lambda cfg: pytest.fail("the scene was made before the check"))
    out = tmp_path / "R"
    expected = _blocked(kind, out, monkeypatch)
    before = sorted(tmp_path.rglob("*"))
    status, err = gsbench(run_args("synthetic/spot", out))
    line = error_line(err)
    assert status == 2 and expected in line, line
    assert "choose another folder with --out (or out: in a config file)" in line
    assert sorted(tmp_path.rglob("*")) == before  # nothing made


# ---- case 5: a full disk ---------------------------------------------------------------------------------------

def _onto_full_disk(name: str):
    """`tempfile.mkstemp` whose file for ``name`` (the temporary file of `atomic_path`) writes to /dev/full, which
    fails every write with ENOSPC as a full disk does."""
    mkstemp = tempfile.mkstemp

    def full(*args, prefix="", **kwargs):
        fd, path = mkstemp(*args, prefix=prefix, **kwargs)
        if prefix == f".{name}.":
            os.close(fd)
            os.unlink(path)
            os.symlink("/dev/full", path)
            fd = os.open(path, os.O_WRONLY)
        return fd, path

    return full


@pytest.fixture(scope="module")
def full_disk(tiny_spot, tmp_path_factory):
    """The quick run with the disk full when it writes its final checkpoint (after the checkpoint of step 10 and the
    training log's lines, the last cut short), then run again: (folder, stderr of the first, of the second)."""
    out = tmp_path_factory.mktemp("full") / "runs"
    folder = folder_of(tiny_spot, out)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(atomic.tempfile, "mkstemp", _onto_full_disk(RunFolder.FINAL_CHECKPOINT))
        status, failed = gsbench(run_args(tiny_spot, out))
    assert status == 2
    left = sorted(p.name for p in folder.iterdir())
    with open(folder / RunFolder.METRICS, "a") as log:
        log.write('{"step": 2')  # a log line the full disk cut short
    status, resumed = gsbench(run_args(tiny_spot, out))
    assert status == 0
    return folder, failed, resumed, left


def test_a_full_disk_is_one_line_naming_the_file_and_the_rerun_resumes_to_the_same_result(full_disk, finished):
    folder, failed, _, left = full_disk
    line = error_line(failed)
    assert line.startswith(f"gsbench: error: {folder / RunFolder.FINAL_CHECKPOINT}: cannot write there: the disk is "
                           "full (no space left on device; ")
    assert " free on the file system of " in line and "fix: free some space there" in line
    assert "run the same command again: a run resumes from its last checkpoint" in line
    assert not [name for name in left if name.endswith(".tmp")]  # no partial file left
    assert RunFolder.CHECKPOINT in left and RunFolder.FINAL_CHECKPOINT not in left
    resumed, straight = (load_checkpoint(RunFolder(f).final_checkpoint)["method"] for f in (folder, finished))
    assert resumed.keys() == straight.keys()
    assert all(torch.equal(resumed[k], straight[k]) for k in straight if isinstance(straight[k], torch.Tensor))
    logged = [json.loads(line)["step"] for line in (folder / RunFolder.METRICS).read_text().splitlines()]
    assert logged == [5, 10, 15, 20]
    assert RunRecord.read(RunFolder(folder).record).metrics == pytest.approx(
        RunRecord.read(RunFolder(finished).record).metrics, rel=1e-9)


def test_a_full_disk_at_a_write_that_is_not_atomic_is_one_line_naming_the_run_folder(tiny_spot, tmp_path):
    folder = folder_of(tiny_spot, tmp_path / "runs")
    folder.mkdir(parents=True)
    (folder / RunFolder.METRICS).symlink_to("/dev/full")  # the training log, appended to line by line
    status, err = gsbench(run_args(tiny_spot, tmp_path / "runs"))
    assert status == 2
    assert error_line(err).startswith(f"gsbench: error: {folder}: cannot write there: the disk is full")
    assert RunRecord.read(RunFolder(folder).record).status == "failed"


def test_atomic_path_keeps_the_earlier_file_when_the_disk_fills(tmp_path, monkeypatch):
    target = tmp_path / "eval.json"
    target.write_text("earlier")
    monkeypatch.setattr(atomic.tempfile, "mkstemp", _onto_full_disk(target.name))
    with pytest.raises(DiskFullError, match=f"{target}: cannot write there: the disk is full"):
        with atomic_path(target) as tmp:
            tmp.write_text("x" * 100_000)
    assert target.read_text() == "earlier" and [p.name for p in tmp_path.iterdir()] == [target.name]


# ---- case 10d: a resumed run says so ------------------------------------------------------------------------

def test_a_resumed_run_says_the_step_it_resumes_from(full_disk):
    folder, _, resumed, _ = full_disk
    assert f"gsbench: resuming at step 10 of 20 from {folder / RunFolder.CHECKPOINT} (" in resumed
    assert "gsbench: training 20 steps" not in resumed


def test_a_run_resumed_after_training_says_so(finished, tiny_spot, tmp_path):
    out = tmp_path / "runs"
    shutil.copytree(finished.parents[3], out)
    folder = out / finished.relative_to(finished.parents[3])
    RunFolder(folder).eval.unlink()
    status, err = gsbench(run_args(tiny_spot, out))
    assert status == 0 and f"gsbench: resuming after training (step 20 of 20) from {RunFolder(folder).final_checkpoint}" \
        in err


# ---- case 6: an edited run folder ---------------------------------------------------------------------------

@pytest.fixture
def edited(finished, tmp_path):
    """A copy of the finished run's ``--out`` whose run folder's config.yaml has another data.max_size."""
    out = tmp_path / "runs"
    shutil.copytree(finished.parents[3], out)
    folder = out / finished.relative_to(finished.parents[3])
    config = yaml.safe_load(RunFolder(folder).config.read_text())
    config["data"]["max_size"] = [640, 480]
    RunFolder(folder).config.write_text(yaml.safe_dump(config, sort_keys=False))
    return out, folder


@pytest.mark.parametrize("command", ["depth", "gaussians", "bench train --run", "run"])
def test_an_edited_config_is_refused_by_every_command_that_reads_the_run_folder(command, edited, tiny_spot):
    out, folder = edited
    config = RunFolder(folder).config
    text = config.read_text()
    args = {"depth": ["depth", str(folder)], "gaussians": ["gaussians", str(folder)],
            "bench train --run": ["bench", "train", "--run", str(folder)], "run": run_args(tiny_spot, out)}[command]
    status, err = gsbench(args)
    line = error_line(err)
    source = "this run's configuration" if command == "run" else "record.json"
    assert status == 2 and line.startswith(f"gsbench: error: {config}: not the configuration of run {folder.name}, "
                                           f"whose folder this is: data.max_size is [640,480] there and [64,48] in "
                                           f"{source}; ")
    assert line.endswith("fix: undo the edit, or delete the file (`gsbench run` of this run writes it again); to run "
                         "with the edited settings, make them a run of its own: gsbench run ... --set "
                         "data.max_size=[640,480]")
    assert config.read_text() == text  # not restored behind the user's back


def test_a_renamed_folder_and_an_edited_record_are_refused(finished, tmp_path):
    renamed = tmp_path / "myrun"
    shutil.copytree(finished, renamed)
    with pytest.raises(Exception, match=f"the folder is named myrun, and its config.yaml and record.json are those of "
                                        f"run {finished.name}; .*fix: rename it to {finished.name}"):
        check_folder_identity(RunFolder(renamed))
    copy = tmp_path / finished.name
    shutil.copytree(finished, copy)
    record = json.loads(RunFolder(copy).record.read_text())
    record["config"]["train"]["iterations"] = 30000
    RunFolder(copy).record.write_text(json.dumps(record))
    with pytest.raises(Exception, match=r"record.json: not the record of run .*: train.iterations is 30000 there and "
                                        r"20 in config.yaml; .*fix: delete it \(`gsbench run` of this run writes it"):
        check_folder_identity(RunFolder(copy))
    RunFolder(copy).record.write_text("{")
    with pytest.raises(Exception, match=r"record.json: unreadable \(.*\): not a file gsbench wrote; fix: delete it"):
        check_folder_identity(RunFolder(copy))
    check_folder_identity(RunFolder(finished))  # the run as it was written


# ---- case 10f: a finished run run again keeps its record ---------------------------------------------------------

def test_a_finished_run_run_again_keeps_its_start_time_and_its_results(finished, tiny_spot, tmp_path):
    out = tmp_path / "runs"
    shutil.copytree(finished.parents[3], out)
    assert gsbench(run_args(tiny_spot, out))[0] == 0  # the copy's record, which names its own paths
    folder = out / finished.relative_to(finished.parents[3])
    record = json.loads(RunFolder(folder).record.read_text())
    record["environment"]["time_utc"] = "2001-02-03T04:05:06+00:00"  # the run's start, long ago
    RunFolder(folder).record.write_text(json.dumps(record))
    status, err = gsbench(run_args(tiny_spot, out))
    assert status == 0 and f"gsbench: finished already: every stage's output is in {folder}" in err
    again = json.loads(RunFolder(folder).record.read_text())
    assert again["environment"]["time_utc"] == "2001-02-03T04:05:06+00:00"
    for key in set(record) - {"environment", "timings", "peak_rss_bytes"}:
        assert again[key] == record[key], key
    measured_again = ("load", "total", "wall_this_invocation")  # the scene is loaded by every invocation
    for key in ("timings", "peak_rss_bytes"):
        assert {k: v for k, v in again[key].items() if k not in measured_again} == \
            {k: v for k, v in record[key].items() if k not in measured_again}
