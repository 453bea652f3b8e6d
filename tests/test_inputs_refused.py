"""Inputs that used to get through (issue 38): cameras that face away from the scene, output folders that
cannot be written. Each is one line naming the file or setting and the fix, before any work."""

from __future__ import annotations

import dataclasses
import errno

import numpy as np
import pytest

import gsbench.atomic as atomic
from gsbench.cli import main
from gsbench.data.camera import Camera
from gsbench.data.dtu import write_cameras_npz
from gsbench.data.images import write_mask, write_rgb
from gsbench.data.loader import check_scene, load_scene
from gsbench.data.synthetic.rigs import look_at
from gsbench.errors import ConfigError, DataError

W, H, N = 16, 12, 4
TURN = np.diag([-1.0, 1.0, -1.0])  # half a turn about the camera's y axis: same centre, looking the other way


def _dtu_folder(root, away: bool):
    K = np.array([[20.0, 0, W / 2], [0, 20.0, H / 2], [0, 0, 1]])
    cameras = []
    for k in range(N):
        R, t = look_at(np.array([3.0 * np.cos(k), 3.0 * np.sin(k), 1.0]), np.zeros(3))
        if away:
            R, t = TURN @ R, TURN @ t
        cameras.append(Camera(K=K, R=R, t=t, width=W, height=H, name=f"{k:06d}.png"))
    (root / "image").mkdir(parents=True)
    (root / "mask").mkdir()
    for k in range(N):
        write_rgb(root / "image" / f"{k:06d}.png", np.full((H, W, 3), 0.5))
        write_mask(root / "mask" / f"{k:03d}.png", np.ones((H, W), bool))
    write_cameras_npz(root / "cameras.npz", cameras, np.diag([2.0, 2.0, 2.0, 1.0]))
    return root


def test_cameras_facing_away_are_found_by_scene_check_and_refused_before_training(tmp_path, capsys):
    facing = load_scene(_dtu_folder(tmp_path / "scan1", away=False), load_images=False)
    assert facing.views_facing_scene() == list(range(N))
    away_root = _dtu_folder(tmp_path / "scan2", away=True)
    away = load_scene(away_root, load_images=False)
    assert away.views_facing_scene() == []
    assert np.allclose([c.center for c in away.cameras], [c.center for c in facing.cameras])
    report = check_scene(away_root)
    assert not report["ok"] and report["cameras_facing_scene"] == 0
    assert "none of its 4 training cameras looks at the scene" in report["errors"][0]
    with pytest.raises(DataError, match="fix: check the camera poses"):
        away.check_cameras_face_scene()
    # the fix the empty visual hull suggests (random_init_region=sphere) no longer trains to a TSDF failure
    out = tmp_path / "runs"
    assert main(["run", "--method", "3dgs", "--scene", str(away_root), "--preset", "quick", "--out", str(out),
                 "--set", "method.random_init_region=sphere"]) == 2
    error = [line for line in capsys.readouterr().err.splitlines() if line.startswith("gsbench: error:")]
    assert len(error) == 1 and "looks at the scene" in error[0] and not out.exists()


def test_half_the_training_cameras_facing_the_scene_is_enough(tmp_path):
    """Issue 65: the others are named in a warning; fewer than half is refused (tests/test_hostile_cameras.py)."""
    scene = load_scene(_dtu_folder(tmp_path / "scan3", away=True), load_images=False)
    scene = dataclasses.replace(scene, cameras=[*load_scene(_dtu_folder(tmp_path / "scan4", away=False),
                                                            load_images=False).cameras[:2], *scene.cameras[2:]])
    assert scene.views_facing_scene() == [0, 1]
    assert "2 of its 4 cameras do not see the scene" in scene.check_cameras_face_scene()


def test_cameras_inside_the_scene_sphere_always_face_it(tmp_path):
    """A layout normalised around its cameras (TnT's, forward-facing captures) puts every camera inside the
    sphere: whichever way they look, they see part of the scene, and nothing is refused."""
    away = load_scene(_dtu_folder(tmp_path / "scan5", away=True), load_images=False)
    inside = dataclasses.replace(away, normalisation=dataclasses.replace(away.normalisation, sphere=10.0))
    assert inside.views_facing_scene() == list(range(N))
    inside.check_cameras_face_scene()


@pytest.mark.parametrize("command", ["run", "report", "eval", "sweep"])
def test_an_output_folder_that_cannot_be_written_is_one_line_before_any_work(command, tmp_path, capsys,
                                                                             monkeypatch):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    out = blocker / "out"
    args = {"run": ["run", "--method", "3dgs", "--scene", "synthetic/spot", "--preset", "quick", "--out", str(out)],
            "report": ["report", str(tmp_path), "--out", str(out)],
            "eval": ["eval", "--mesh", str(blocker), "--scene", "synthetic/spot", "--out", str(out / "r.json")],
            "sweep": ["sweep", "configs/sweeps/ibgs_k.yaml", "--out", str(out)]}[command]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "a-file is a file, not a folder" in err and "--out" in err


def test_a_read_only_folder_is_refused(tmp_path, monkeypatch):
    monkeypatch.setattr(atomic.os, "access", lambda path, mode: False)  # as on a read-only file system
    with pytest.raises(Exception, match="is not writable .*fix: choose another folder with --out"):
        atomic.check_writable(tmp_path / "report", "--out")


def test_a_file_system_that_takes_no_folders_is_refused_and_the_probe_leaves_nothing(tmp_path, monkeypatch):
    """Permission bits pass on /proc as root, where every mkdir fails (ENOENT): `--out /proc/x` crashed with a
    traceback in the run folder's lock before the probe."""
    atomic.check_writable(tmp_path / "runs", "--out")
    assert list(tmp_path.iterdir()) == []

    def refuse(**_kwargs):
        raise FileNotFoundError(2, "No such file or directory")

    monkeypatch.setattr(atomic.tempfile, "mkdtemp", refuse)
    with pytest.raises(ConfigError, match=r"takes no new folders \(no such file or directory.*--out"):
        atomic.check_writable(tmp_path / "runs", "--out")


def test_a_full_disk_is_named_when_the_folder_probe_finds_it(tmp_path, monkeypatch):
    def full(**_kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomic.tempfile, "mkdtemp", full)
    with pytest.raises(atomic.DiskFullError, match="the disk is full"):
        atomic.check_writable(tmp_path / "runs", "--out")


def test_eval_of_a_mesh_without_faces_names_the_cli_fix_and_that_fix_works(tiny_spot, tmp_path, capsys):
    """The message for a point cloud names an option the command line has (``--points``), and it works."""
    import trimesh

    cloud = tmp_path / "points.ply"
    trimesh.PointCloud(trimesh.creation.icosphere(subdivisions=3).vertices * 0.5).export(cloud)
    assert main(["eval", "--mesh", str(cloud), "--scene", str(tiny_spot), "--evaluator", "dtu_chamfer"]) == 2
    assert "gsbench eval --points --evaluator dtu_chamfer" in capsys.readouterr().err
    assert main(["eval", "--mesh", str(cloud), "--scene", str(tiny_spot), "--points"]) == 2  # others need faces
    assert "fix: add --evaluator dtu_chamfer" in capsys.readouterr().err
    assert main(["eval", "--mesh", str(cloud), "--scene", str(tiny_spot), "--points", "--evaluator",
                 "dtu_chamfer"]) == 0
    assert "dtu_chamfer@1" in capsys.readouterr().out
