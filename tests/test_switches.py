"""The ``GSBENCH_*`` switches (gsbench/switches.py, docs/switches.md): one registry that alone reads them; every
result-changing one in the record and held fixed over a run folder's resumes; the speed-only ones leave a run
bit-identical. And the config fields added after records existed: shown by ``gsbench config``, out of the run id
at their defaults."""

from __future__ import annotations

import ast
import dataclasses
import json
import re
from pathlib import Path

import pytest
import yaml

from gsbench.cli import main
from gsbench.config.run_config import ADDED_AFTER_RECORDS, completed_config, run_id
from gsbench.errors import ConfigError
from gsbench.registry import METHODS
from gsbench.run_folder import RunFolder
from gsbench.runs.finished_run import read_run_config
from gsbench.runs.records import capture_environment, check_folder_switches
from gsbench.runs.runner import load_run_scene, resolve_run, run, run_dir
from gsbench.switches import DATA, KINDS, ON_OFF, SWITCHES, departures, result_switches

ROOT = Path(__file__).resolve().parent.parent
PACKAGE_SOURCES = ("gsbench", "methods", "evaluators")
REGISTRY = ROOT / "gsbench" / "switches.py"
RESULT = [s for s in SWITCHES if s.kind == "result"]
SPEED = [s for s in SWITCHES if s.kind == "speed"]
ENUMERATED = [s for s in SWITCHES if s.values]
# 2DGS (the surfel kernel, with distortion) on the tiny scene; mesh_stats keeps the evaluation short
QUICK = ["data.downscale=1", "method.random_init_points=2000", "train.iterations=60", "train.checkpoint_every=0",
         "train.log_every=10", "mesh.voxel_size=0.02", "mesh.sdf_trunc=0.08", "eval.evaluators=[mesh_stats]",
         "threads=1"]


# the fields added after records that a SuGaR config has: its own and every method's
SUGAR_FIELDS = [(owner, key, default) for owner, key, default in ADDED_AFTER_RECORDS if owner in (None, "sugar")]


def _section(config: dict, key: str) -> tuple[dict, str]:
    """(the section of ``config`` holding the dotted ``key``, the key's last part)."""
    *parents, name = key.split(".")
    for part in parents:
        config = config[part]
    return config, name


def _value(config: dict, key: str):
    section, name = _section(config, key)
    return section[name]


def _other_value(switch) -> str:
    return next(v for v in switch.values if v != switch.default)


@pytest.fixture
def at_defaults(monkeypatch):
    for switch in RESULT:
        monkeypatch.delenv(switch.name, raising=False)
    return monkeypatch


def test_the_registry_names_each_switch_once_with_its_kind_and_default():
    names = [s.name for s in SWITCHES]
    assert len(set(names)) == len(names) == 14 and all(n.startswith("GSBENCH_") for n in names)
    assert all(s.kind in KINDS and s.selects for s in SWITCHES)
    assert all(s.default == s.values[0] for s in ENUMERATED)  # the fast path first (gsbench.native.impl_choice)
    assert all(len(s.values) == 2 for s in RESULT) and all(s.values == ON_OFF for s in SPEED)


def _package_files() -> list[Path]:
    return [p for root in PACKAGE_SOURCES for p in sorted((ROOT / root).rglob("*.py"))]


def test_no_gsbench_variable_is_read_outside_the_registry():
    """Outside gsbench/switches.py no string is a GSBENCH_* name (the key of a read, or a constant holding one)
    and no read of the environment names one; every GSBENCH_* the package mentions is registered."""
    registered = {s.name for s in SWITCHES}
    problems = []
    for path in _package_files():
        text = path.read_text()
        rel = path.relative_to(ROOT)
        problems += [f"{rel}: mentions {name}, not in gsbench.switches" for name in
                     set(re.findall(r"GSBENCH_[A-Z_]*[A-Z]", text)) - registered]
        if path == REGISTRY:
            continue
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and \
                    re.fullmatch(r"GSBENCH_[A-Z_]+", node.value.strip()):
                problems.append(f"{rel}:{node.lineno}: the name {node.value} outside the registry")
            if isinstance(node, ast.Attribute) and node.attr in ("environ", "getenv", "putenv") and \
                    isinstance(node.value, ast.Name) and node.value.id == "os":
                line = text.splitlines()[node.lineno - 1]
                if "GSBENCH" in line:
                    problems.append(f"{rel}:{node.lineno}: reads a GSBENCH_* switch itself: {line.strip()}")
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("switch", ENUMERATED, ids=lambda s: s.name)
def test_a_bad_value_names_the_variable_and_the_allowed_values(switch, monkeypatch):
    monkeypatch.setenv(switch.name, "bogus")
    with pytest.raises(ConfigError, match=rf"{switch.name}='bogus' is not one of .*{switch.values[0]}.*unset it"):
        switch.value()
    monkeypatch.setenv(switch.name, f" {switch.default.upper()} ")
    assert switch.value() == switch.default
    monkeypatch.setenv(switch.name, "")
    assert switch.value() == switch.default


def test_on_off_switches_take_the_usual_spellings(monkeypatch):
    (switch, *_) = [s for s in SWITCHES if s.values == ON_OFF]
    for text, value in (("1", "on"), ("true", "on"), ("yes", "on"), ("0", "off"), ("False", "off"), ("no", "off")):
        monkeypatch.setenv(switch.name, text)
        assert switch.value() == value


def test_a_path_switch_takes_any_folder(monkeypatch, tmp_path):
    monkeypatch.setenv(DATA.name, str(tmp_path / "Any Folder"))
    assert DATA.value() == str(tmp_path / "Any Folder")


@pytest.mark.parametrize("switch", RESULT, ids=lambda s: s.name)
def test_setting_a_result_changing_switch_changes_the_record(switch, at_defaults):
    """The record's environment holds every result switch: at the defaults all of them at their defaults (so such
    a record is recognisable); set, this one at its value, with a warning at the run's start."""
    made_at_defaults = capture_environment(1)["switches"]
    assert made_at_defaults == {s.name: s.default for s in RESULT} and departures() == []
    at_defaults.setenv(switch.name, _other_value(switch))
    switched = capture_environment(1)["switches"]
    assert switched != made_at_defaults and switched[switch.name] == _other_value(switch)
    (warning,) = departures()
    assert warning.startswith(f"{switch.name}={_other_value(switch)} (default {switch.default})")


def test_a_run_folder_refuses_to_resume_under_other_switches(at_defaults, tmp_path):
    files = RunFolder(tmp_path / "run")
    files.path.mkdir()
    files.config.write_text("{}")
    check_folder_switches(files)  # nothing made yet: the switches are stored
    assert json.loads(files.switches.read_text()) == result_switches()
    files.stages.write_text("{}")
    check_folder_switches(files)  # the same switches: it resumes
    at_defaults.setenv("GSBENCH_SSIM", "reference")
    with pytest.raises(ConfigError, match=r"was run with GSBENCH_SSIM=fused and this process has GSBENCH_SSIM=reference"
                                          r".*fix: set GSBENCH_SSIM=fused again .*remove the folder"):
        check_folder_switches(files)
    files.stages.unlink()  # its outputs removed (a sweep's --other-code rerun): it starts afresh under the new ones
    check_folder_switches(files)
    assert json.loads(files.switches.read_text())["GSBENCH_SSIM"] == "reference"


def test_a_folder_made_before_switches_were_stored_counts_as_made_at_the_defaults(at_defaults, tmp_path):
    files = RunFolder(tmp_path / "run")
    files.path.mkdir()
    files.final_checkpoint.write_bytes(b"")
    at_defaults.setenv("GSBENCH_EIGEN", "reference")
    with pytest.raises(ConfigError, match="was run with GSBENCH_EIGEN=fast"):
        check_folder_switches(files)
    assert not files.switches.exists()
    at_defaults.delenv("GSBENCH_EIGEN")
    check_folder_switches(files)
    assert json.loads(files.switches.read_text()) == {s.name: s.default for s in RESULT}


def _record(tiny_spot, out: Path) -> tuple[dict, Path]:
    cfg = resolve_run("2dgs", str(tiny_spot), preset="quick", overrides=QUICK)
    cfg.out = str(out)
    record = run(cfg, echo=lambda *a: None).to_dict()
    assert record["status"] == "ok"
    return record, run_dir(cfg)


def test_speed_switches_leave_a_run_bit_identical_and_a_resume_under_other_switches_is_refused(
        tiny_spot, tmp_path, monkeypatch, restore_threads):
    """A quick 2DGS run, then the same run with every speed switch flipped (the decoded-image cache filled first, so
    the run reads it): the same record but for times, paths and the environment. Then the first run's folder
    refuses a result switch that differs from its own."""
    for switch in RESULT:
        monkeypatch.delenv(switch.name, raising=False)
    plain, folder = _record(tiny_spot, tmp_path / "a")
    monkeypatch.setenv(DATA.name, str(tmp_path / "cache"))
    for switch in SPEED:
        monkeypatch.setenv(switch.name, "off" if switch.value() == "on" else "on")
    cfg = resolve_run("2dgs", str(tiny_spot), preset="quick", overrides=QUICK)
    load_run_scene(cfg)  # with the image cache on: fills it
    flipped, _ = _record(tiny_spot, tmp_path / "b")
    assert list((tmp_path / "cache" / "decoded").glob("*.npz"))
    def same(record):  # all but the times, memory, machine and paths
        config = {k: v for k, v in record["config"].items() if k != "out"}
        mesh = {k: v for k, v in record["mesh"].items() if k not in ("path", "checkpoint")}
        points = [{k: v for k, v in point.items() if not k.endswith("_seconds")} for point in record["points"]]
        volatile = ("timings", "peak_rss_bytes", "environment", "it_per_s", "config", "mesh", "points")
        return {k: v for k, v in record.items() if k not in volatile}, config, mesh, points

    assert same(flipped) == same(plain) and plain["mesh"]["sha256"] and plain["metrics"]["faces"] > 0
    assert plain["environment"]["switches"] == {s.name: s.default for s in RESULT}
    monkeypatch.setenv("GSBENCH_PROJECTION", "torch")
    cfg.out = str(tmp_path / "a")
    with pytest.raises(ConfigError, match=re.escape(f"{folder} was run with GSBENCH_PROJECTION=fused")):
        run(cfg, echo=lambda *a: None)


def test_run_ids_leave_out_fields_added_after_records_only_at_their_defaults_and_for_their_method():
    base = {"scene": "s", "method": {"name": "sugar", "knn_k": 16}, "threads": 4}
    with_later = {**base, "method": {**base["method"], "refinement": "none", "refine_triangles": 50_000}}
    assert run_id(with_later) == run_id(base)
    assert run_id({**base, "method": {**base["method"], "refinement": "short"}}) != run_id(base)
    assert with_later["method"]["refinement"] == "none"  # the config itself is left as it was
    other = {"scene": "s", "method": {"name": "3dgs"}}
    assert run_id({**other, "method": {"name": "3dgs", "refinement": "none"}}) != run_id(other)


def test_a_recorded_config_is_completed_with_the_later_fields_of_its_method():
    """What a record made before the fields was run with (the report compares runs by their configs)."""
    cfg = resolve_run("sugar", "synthetic/dtu-bunny", preset="cpu")
    recorded = cfg.to_dict()
    for _, key, _ in SUGAR_FIELDS:
        section, name = _section(recorded, key)
        del section[name]
    assert completed_config(recorded) == cfg.to_dict() and run_id(completed_config(recorded)) == run_id(recorded)
    assert "refinement" not in recorded["method"]
    other = resolve_run("3dgs", "synthetic/dtu-bunny", preset="cpu").to_dict()
    assert completed_config(other) == other


def test_gsbench_config_shows_every_field_a_user_can_set(capsys):
    """SuGaR's refinement fields, added after records existed, are shown at their defaults like every other."""
    assert main(["config", "--method", "sugar", "--scene", "synthetic/dtu-bunny"]) == 0
    shown = yaml.safe_load(capsys.readouterr().out)
    assert set(shown["method"]) == {"name"} | {f.name for f in dataclasses.fields(METHODS.get("sugar").Config)}
    assert {key: _value(shown, key) for _, key, _ in SUGAR_FIELDS} == {key: default for _, key, default in SUGAR_FIELDS}


def test_a_finished_run_whose_config_lacks_a_later_field_is_read_back_with_its_id(tmp_path):
    """A run folder from before the refinement fields: its config.yaml lacks them; read back, they are at their
    defaults and the run id is the folder's."""
    cfg = resolve_run("sugar", "synthetic/dtu-bunny", preset="cpu")
    old = cfg.to_dict()
    for _, key, _ in SUGAR_FIELDS:
        section, name = _section(old, key)
        del section[name]
    files = RunFolder(tmp_path / run_id(old))
    files.path.mkdir()
    files.config.write_text(yaml.safe_dump(old, sort_keys=False))
    files.final_checkpoint.write_bytes(b"")
    read, _ = read_run_config(files.path, "test")
    assert read.method["refinement"] == "none" and read.run_id == files.path.name == cfg.run_id


def test_a_finished_tnt_run_from_before_the_frame_key_is_read_back_in_its_frame(tmp_path):
    """A TnT run folder from before data.tnt_frame: read back (`gsbench depth`, the report's pictures), it is in the
    extent frame it trained in, not the COLMAP frame configs/datasets/tnt.yaml now selects (docs/design.md §12.1)."""
    cfg = resolve_run("2dgs", "synthetic/tnt-rig-spot", preset="quick", overrides=["data.tnt_frame=extent"])
    old = cfg.to_dict()
    del old["data"]["tnt_frame"]
    files = RunFolder(tmp_path / run_id(old))
    files.path.mkdir()
    files.config.write_text(yaml.safe_dump(old, sort_keys=False))
    files.final_checkpoint.write_bytes(b"")
    read, _ = read_run_config(files.path, "test")
    assert read.data.tnt_frame == "extent" and read.run_id == files.path.name == cfg.run_id
    assert resolve_run("2dgs", "synthetic/tnt-rig-spot", preset="quick").data.tnt_frame == "colmap"


def test_docs_list_every_switch_with_its_values_and_kind():
    rows = {}
    for line in (ROOT / "docs" / "switches.md").read_text().splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if len(cells) == 4 and cells[0].startswith("`GSBENCH_"):
            rows[cells[0].strip("`")] = (cells[2], cells[3])
    assert set(rows) == {s.name for s in SWITCHES}
    for s in SWITCHES:
        values, kind = rows[s.name]
        assert kind == s.kind, s.name
        assert values == ", ".join(f"`{v}`" for v in s.values) if s.values else s.default in values, s.name
