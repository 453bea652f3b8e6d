"""Run records: schema round trip, atomic writes that never leave a partial file, environment."""

import json
import os

import pytest

from gsbench.runs.records import RunRecord, capture_environment, sha256_file, write_json_atomic


def test_record_round_trip(tmp_path):
    rec = RunRecord(run_id="abc", method="toy", scene="synthetic/spot", dataset="dtu", seed=0, status="ok",
                    metrics={"chamfer": 0.5}, timings={"train": 1.0})
    path = tmp_path / "runs" / "record.json"
    rec.write(path)
    back = RunRecord.read(path)
    assert back == rec
    assert json.loads(path.read_text())["schema_version"] == 1


def test_bad_status_is_rejected(tmp_path):
    with pytest.raises(ValueError, match="status"):
        RunRecord(run_id="a", method="m", scene="s", dataset="d", seed=0, status="done").write(tmp_path / "r.json")


def test_atomic_write_keeps_old_file_on_failure(tmp_path):
    path = tmp_path / "r.json"
    write_json_atomic(path, {"a": 1})
    with pytest.raises(TypeError):
        write_json_atomic(path, {"a": object()})
    assert json.loads(path.read_text()) == {"a": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["r.json"]  # no temp file left behind


def test_environment_and_sha(tmp_path):
    env = capture_environment(threads=2)
    for key in ("gsbench", "git_commit", "python", "packages", "cpu", "threads", "time_utc"):
        assert key in env
    assert env["threads"] == 2
    f = tmp_path / "x.bin"
    f.write_bytes(b"abc")
    assert sha256_file(f) == "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
    assert os.path.exists(f)
