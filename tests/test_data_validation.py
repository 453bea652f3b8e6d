"""Bad scene folders fail with one-line DataErrors that name the offending file and the fix."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from gsbench.data.camera import Camera
from gsbench.data.colmap import write_colmap_model
from gsbench.data.dtu import write_cameras_npz
from gsbench.data.images import write_mask, write_rgb
from gsbench.data.loader import check_scene, load_scene
from gsbench.data.synthetic.rigs import look_at
from gsbench.errors import DataError

W, H, N = 16, 12, 3


def _cameras():
    K = np.array([[20.0, 0, W / 2], [0, 20.0, H / 2], [0, 0, 1]])
    cams = []
    for k in range(N):
        R, t = look_at(np.array([3.0 * np.cos(k), 3.0 * np.sin(k), 1.0]), np.zeros(3))
        cams.append(Camera(K=K, R=R, t=t, width=W, height=H, name=f"{k:06d}.png"))
    return cams


def _images(folder):
    folder.mkdir(parents=True)
    for k in range(N):
        write_rgb(folder / f"{k:06d}.png", np.full((H, W, 3), 0.5))


@pytest.fixture
def dtu(tmp_path):
    root = tmp_path / "scan7"
    _images(root / "image")
    (root / "mask").mkdir()
    for k in range(N):
        write_mask(root / "mask" / f"{k:03d}.png", np.ones((H, W), bool))
    write_cameras_npz(root / "cameras.npz", _cameras(), np.diag([2.0, 2.0, 2.0, 1.0]))
    return root


@pytest.fixture
def tnt(tmp_path):
    root = tmp_path / "Barn"
    _images(root / "images")
    write_colmap_model(root / "sparse" / "0", _cameras(), np.zeros((4, 3)), np.ones((4, 3)))
    return root


def _expect(root, *fragments):
    with pytest.raises(DataError) as info:
        load_scene(root)
    message = str(info.value)
    assert "\n" not in message and "fix:" in message
    for fragment in fragments:
        assert str(fragment) in message
    return message


def test_valid_fixtures_load(dtu, tnt):
    scene = load_scene(dtu)
    assert scene.fmt == "dtu" and len(scene.cameras) == N and scene.normalisation.scale == 2.0
    assert scene.gt is None and scene.masks[0].all()
    scene = load_scene(tnt)
    assert scene.fmt == "tnt" and len(scene.cameras) == N and scene.gt is None and len(scene.points) == 4


def test_image_count_differs_from_cameras(dtu, tnt):
    write_rgb(dtu / "image" / "000009.png", np.zeros((H, W, 3)))
    write_mask(dtu / "mask" / "009.png", np.ones((H, W), bool))
    _expect(dtu, dtu / "cameras.npz", "4 images")
    write_rgb(tnt / "images" / "extra.png", np.zeros((H, W, 3)))
    _expect(tnt, tnt / "images", "3 cameras")


def test_non_finite_world_mat(dtu):
    data = dict(np.load(dtu / "cameras.npz"))
    data["world_mat_1"][0, 0] = np.inf
    np.savez(dtu / "cameras.npz", **data)
    _expect(dtu, dtu / "cameras.npz", "world_mat_1")


def test_singular_projection(dtu):
    data = dict(np.load(dtu / "cameras.npz"))
    data["world_mat_2"][2, :3] = data["world_mat_2"][0, :3]
    np.savez(dtu / "cameras.npz", **data)
    _expect(dtu, dtu / "cameras.npz", "world_mat_2", "rank < 3")


def test_non_positive_focal(tnt):
    cams = _cameras()
    cams[0] = Camera(K=np.diag([-20.0, 20.0, 1.0]), R=cams[0].R, t=cams[0].t, width=W, height=H, name=cams[0].name)
    shutil.rmtree(tnt / "sparse")
    write_colmap_model(tnt / "sparse" / "0", cams, np.zeros((1, 3)), np.ones((1, 3)))
    _expect(tnt, tnt / "sparse" / "0" / "cameras.bin", "focal")


def test_missing_masks(dtu):
    (dtu / "mask" / "001.png").unlink()
    _expect(dtu, dtu / "mask", "2 masks for 3 images")
    shutil.rmtree(dtu / "mask")
    _expect(dtu, dtu / "mask", "not found")


def test_unreadable_image(dtu, tnt):
    (dtu / "image" / "000001.png").write_bytes(b"not a png")
    _expect(dtu, dtu / "image" / "000001.png", "unreadable")
    (tnt / "images" / "000002.png").write_bytes(b"")
    _expect(tnt, tnt / "images" / "000002.png", "unreadable")


def test_missing_cameras_npz(dtu):
    (dtu / "cameras.npz").unlink()
    _expect(dtu, dtu / "cameras.npz", "not found")


def test_unsupported_camera_model(tnt):
    import pycolmap

    rec = pycolmap.Reconstruction(str(tnt / "sparse" / "0"))
    distorted = pycolmap.Camera(model="OPENCV", width=W, height=H, params=[20, 20, W / 2, H / 2, 0.1, 0, 0, 0], camera_id=1)
    rec.cameras[1] = distorted
    rec.write_binary(str(tnt / "sparse" / "0"))
    message = _expect(tnt, tnt / "sparse" / "0" / "cameras.bin", "OPENCV", "image_undistorter")
    assert "undistorted" in message


def test_zero_distortion_model_is_accepted(tnt):
    import pycolmap

    rec = pycolmap.Reconstruction(str(tnt / "sparse" / "0"))
    rec.cameras[1] = pycolmap.Camera(model="OPENCV", width=W, height=H, params=[20, 20, W / 2, H / 2, 0, 0, 0, 0], camera_id=1)
    rec.write_binary(str(tnt / "sparse" / "0"))
    assert np.allclose(load_scene(tnt).cameras[0].K, _cameras()[0].K)


def test_image_size_mismatch(dtu, tnt):
    write_rgb(dtu / "image" / "000002.png", np.zeros((H + 2, W, 3)))
    _expect(dtu, dtu / "image" / "000002.png", f"{W}x{H + 2}")
    write_rgb(tnt / "images" / "000001.png", np.zeros((H, W + 1, 3)))
    _expect(tnt, tnt / "images" / "000001.png", f"{W + 1}x{H}")


def test_unknown_layout_and_check_report(tmp_path, dtu):
    _expect(tmp_path, tmp_path, "expected")
    (dtu / "cameras.npz").unlink()
    report = check_scene(dtu)
    assert not report["ok"] and report["format"] == "dtu" and str(dtu / "cameras.npz") in report["errors"][0]
