"""Loading only loads: `load_scene` reads a built-in scene's cache folder and writes nothing; the runner makes a
missing one first, in its own step (`make_run_scene`, the function ``gsbench scene make`` runs), then loads it."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest
import trimesh

import gsbench.runs.runner as runner
from gsbench.cli import main
from gsbench.data.loader import load_scene
from gsbench.data.meta import write_meta
from gsbench.data.synthetic import generator, make
from gsbench.data.synthetic.make import ensure_scene, make_scene
from gsbench.errors import DataError
from gsbench.runs.runner import load_run_scene, make_run_scene, resolve_run

TINY_RES = 0.04  # the default size as a share of DTU's 1600x1200: 64x48


def test_loading_a_builtin_scene_not_made_yet_names_the_command_and_writes_nothing(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    monkeypatch.setenv("GSBENCH_DATA", str(cache))
    with pytest.raises(DataError, match=r"synthetic/spot: built-in scene not made yet .*`gsbench scene make synthetic/spot`"):
        load_scene("synthetic/spot", load_images=False)
    with pytest.raises(DataError, match="no built-in scene of that name"):
        load_scene("synthetic/no-such-scene")
    assert not cache.exists()


def test_the_loader_does_not_import_the_generator():
    code = "import sys, gsbench.data.loader; print(sorted(m for m in sys.modules if m.startswith('gsbench.data.synthetic.')))"
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert loaded.strip() == "['gsbench.data.synthetic.builtin']"


def test_the_runner_makes_a_missing_builtin_scene_once_then_loads_it(tmp_path, monkeypatch, capsys):
    cache = tmp_path / "cache"
    monkeypatch.setenv("GSBENCH_DATA", str(cache))
    monkeypatch.setattr(generator, "DEFAULT_RES", TINY_RES)
    cfg = resolve_run("3dgs", "synthetic/spot", preset="quick", overrides=["data.downscale=1"])
    make_run_scene(cfg)
    err = capsys.readouterr().err  # not a terminal: tqdm is silent, the rendering's progress lines are not
    assert "gsbench: making synthetic/spot (first use" in err
    assert re.search(r"^rendering \S*spot: view 49/49 \(100%\) .* done in \S+$", err, re.M), err
    folder = cache / "synthetic" / "spot"
    meta = (folder / "gsbench_scene.json").stat().st_mtime_ns
    scene = load_run_scene(cfg, load_images=False)
    assert scene.root == folder and len(scene.cameras) == 49 and scene.cameras[0].width == 64
    make_run_scene(cfg)  # made: nothing is written again, nothing is printed
    assert capsys.readouterr().err == "" and (folder / "gsbench_scene.json").stat().st_mtime_ns == meta
    assert make_scene("synthetic/spot") == folder == ensure_scene("synthetic/spot")  # `gsbench scene make`'s folder
    assert ensure_scene(str(tmp_path)) == tmp_path  # a folder is left as it is
    assert sorted(p.name for p in (cache / "synthetic").iterdir()) == ["spot"]  # no temporary folder left


def test_a_maker_that_finishes_second_leaves_the_first_makers_folder_untouched(tmp_path, monkeypatch):
    """Two sweep workers make one scene: the one finishing first renames its folder into place and starts
    reading it; the second must discard its own copy, not swap the folder out from under the first's reader."""
    cache = tmp_path / "cache"
    monkeypatch.setenv("GSBENCH_DATA", str(cache))
    folder = cache / "synthetic" / "spot"
    first_maker = {"finished": False}

    def write_meta_only(plan, into):  # the scene's meta and one image stand in for the rendering
        if not first_maker["finished"]:  # while the second maker writes, the first finishes and its reader opens a file
            first_maker["finished"] = True
            make_scene("synthetic/spot")
            (folder / "open-in-the-first-reader").touch()
        write_meta(into, generator.plan_meta(plan))
        (into / "000000.png").touch()

    monkeypatch.setattr(make, "write_scene", write_meta_only)
    assert make_scene("synthetic/spot") == folder
    assert (folder / "open-in-the-first-reader").is_file()
    assert sorted(p.name for p in (cache / "synthetic").iterdir()) == ["spot"]  # the second copy is gone


def test_run_makes_the_scene_before_it_reads_it(tmp_path, monkeypatch):
    steps = []

    class Stop(Exception):
        pass

    def load(cfg, **_kwargs):
        steps.append("load")
        raise Stop

    monkeypatch.setattr(runner, "make_run_scene", lambda cfg: steps.append(f"make {cfg.scene}"))
    monkeypatch.setattr(runner, "load_run_scene", load)
    cfg = resolve_run("3dgs", "synthetic/spot", preset="quick")
    cfg.out = str(tmp_path / "runs")
    with pytest.raises(Stop):
        runner.run(cfg)
    assert steps == ["make synthetic/spot", "load"]


def test_eval_makes_a_missing_builtin_scene_before_it_loads_it(tmp_path, monkeypatch, capsys):
    cache = tmp_path / "cache"
    monkeypatch.setenv("GSBENCH_DATA", str(cache))
    monkeypatch.setattr(generator, "DEFAULT_RES", TINY_RES)
    mesh = tmp_path / "box.ply"
    trimesh.creation.box(extents=(0.5, 0.5, 0.5)).export(mesh)
    assert main(["eval", "--mesh", str(mesh), "--scene", "synthetic/spot", "--evaluator", "mesh_stats"]) == 0
    assert "mesh_stats" in capsys.readouterr().out and (cache / "synthetic" / "spot" / "gsbench_scene.json").is_file()
