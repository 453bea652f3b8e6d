"""Partly wrong cameras (issue 65, case 3): a camera that does not see the scene is named by ``scene check`` (a
warning, the scene still ok), and a run whose training cameras mostly do not see it stops before training with one
line. "Sees the scene": the scene sphere reaches into the camera's view pyramid (`Camera.sees_sphere`)."""

from __future__ import annotations

import numpy as np
import pytest

from gsbench.cli import main
from gsbench.data.camera import MIN_TRAIN_VIEWS_SEEING, Camera, name_list
from gsbench.data.dtu import write_cameras_npz
from gsbench.data.images import write_mask, write_rgb
from gsbench.data.loader import check_scene, load_scene
from gsbench.data.synthetic.rigs import look_at
from gsbench.errors import DataError
from gsbench.runs import runner

W, H, VIEWS = 16, 12, 49
K = np.array([[20.0, 0, W / 2], [0, 20.0, H / 2], [0, 0, 1]])
TURN = np.diag([-1.0, 1.0, -1.0])  # half a turn about the camera's own y axis: same centre, looking the other way


def dtu_folder(root, turned=()):
    """A DTU-layout scene of `VIEWS` cameras on a ring about the object, looking at it, except those in ``turned``."""
    cameras = []
    for k in range(VIEWS):
        angle = 2 * np.pi * k / VIEWS
        R, t = look_at(np.array([3.0 * np.cos(angle), 3.0 * np.sin(angle), 1.0]), np.zeros(3))
        if k in turned:
            R, t = TURN @ R, TURN @ t
        cameras.append(Camera(K=K, R=R, t=t, width=W, height=H, name=f"{k:06d}.png"))
    (root / "image").mkdir(parents=True)
    (root / "mask").mkdir()
    for k in range(VIEWS):
        write_rgb(root / "image" / f"{k:06d}.png", np.full((H, W, 3), 0.5))
        write_mask(root / "mask" / f"{k:03d}.png", np.ones((H, W), bool))
    write_cameras_npz(root / "cameras.npz", cameras, np.diag([2.0, 2.0, 2.0, 1.0]))
    return root


def test_one_turned_camera_is_named_by_scene_check_and_the_scene_stays_ok(tmp_path):
    root = dtu_folder(tmp_path / "scan1", turned={7})
    report = check_scene(root)
    assert report["ok"] and report["errors"] == [] and report["cameras_facing_scene"] == VIEWS - 1
    (warning,) = report["warnings"]
    assert "1 of its 49 cameras do not see the scene" in warning and warning.split("): ")[1].startswith("000007.png;")
    assert "fix: check the camera poses" in warning
    assert check_scene(dtu_folder(tmp_path / "scan2"))["warnings"] == []


def test_a_run_whose_training_cameras_mostly_do_not_see_the_scene_stops_before_training(tmp_path, capsys):
    turned = set(range(5, VIEWS))  # 44 of 49
    root = dtu_folder(tmp_path / "scan3", turned=turned)
    report = check_scene(root)
    assert not report["ok"] and report["cameras_facing_scene"] == 5
    out = tmp_path / "runs"
    assert main(["--threads", "1", "run", "--method", "3dgs", "--scene", str(root), "--preset", "quick",
                 "--out", str(out)]) == 2
    (err,) = [line for line in capsys.readouterr().err.splitlines() if line.startswith("gsbench: error:")]
    train = load_scene(root, load_images=False, holdout_every=8).train_views  # a scene without GT holds out every 8th
    seeing = len([i for i in train if i < 5])
    assert f"only {seeing} of its {len(train)} training cameras look at the scene" in err
    assert "000005.png, 000006.png, 000007.png, 000009.png, 000010.png and " in err
    assert "fix: check the camera poses" in err
    assert not out.exists()


def test_the_threshold_is_half_of_the_training_cameras(tmp_path):
    half = VIEWS // 2  # 24 of 49 turned: 25 see the scene, enough
    scene = load_scene(dtu_folder(tmp_path / "scan4", turned=set(range(half))), load_images=False)
    assert MIN_TRAIN_VIEWS_SEEING == 0.5
    assert "24 of its 49 cameras do not see the scene" in scene.check_cameras_face_scene()
    scene = load_scene(dtu_folder(tmp_path / "scan5", turned=set(range(half + 1))), load_images=False)
    with pytest.raises(DataError, match="only 24 of its 49 training cameras look at the scene"):
        scene.check_cameras_face_scene()


def test_a_camera_sees_the_sphere_when_it_reaches_into_its_view_pyramid():
    """Outside the sphere and looking past it, with the sphere's centre beside the camera (z = 0): part of the
    sphere is in the picture, so the camera sees it (the centre-in-front test said it did not)."""
    def camera(eye, target):
        R, t = look_at(np.asarray(eye, float), np.asarray(target, float))
        return Camera(K=np.array([[8.0, 0, 8], [0, 8.0, 6], [0, 0, 1]]), R=R, t=t, width=16, height=12)

    origin = np.zeros(3)
    assert camera([3, 0, 0], [0, 0, 0]).sees_sphere(origin, 1.0)
    assert not camera([3, 0, 0], [6, 0, 0]).sees_sphere(origin, 1.0)  # looking away
    beside = camera([0, -1.2, 0], [1, -1.2, 0])  # looking along x, the sphere 1.2 to its right, its centre at z = 0
    assert beside.sees_sphere(origin, 1.0) and not beside.sees_sphere(origin, 0.5)
    assert not camera([3, 0, 0], [3, 5, 0]).sees_sphere(origin, 1.0)  # looking sideways, the sphere out of the picture
    assert camera([0.5, 0, 0], [3, 0, 0]).sees_sphere(origin, 1.0)  # inside the sphere: always


def test_name_list_names_the_first_few_and_counts_the_others():
    assert name_list(["a", "b"]) == "a, b"
    assert name_list([f"v{k}" for k in range(8)]) == "v0, v1, v2, v3, v4 and 3 more"


def test_a_run_warns_of_the_cameras_that_do_not_see_the_scene(tmp_path, capsys, monkeypatch):
    root = dtu_folder(tmp_path / "scan6", turned={7})

    def stop(*_args):
        raise RuntimeError("stopped after the camera check")

    monkeypatch.setattr(runner, "plan_run_evaluation", stop)
    with pytest.raises(RuntimeError, match="stopped after the camera check"):
        main(["--threads", "1", "run", "--method", "3dgs", "--scene", str(root), "--preset", "quick",
              "--out", str(tmp_path / "runs")])
    (warning,) = [line for line in capsys.readouterr().err.splitlines() if line.startswith("gsbench: warning:")]
    assert "scene 'scan6': 1 of its 49 cameras do not see the scene" in warning and "): 000007.png;" in warning
