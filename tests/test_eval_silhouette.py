"""silhouette: mask IoU of the mesh's pixel-centre silhouettes and its surface area outside the visual hull."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from gsbench.data.camera import Camera, Normalisation, Scene
from gsbench.errors import EvaluationError
from gsbench.evaluators.resolve import get_evaluator
from gsbench.evaluators.silhouette import Silhouette

SIZE = 40  # pixels, square images


def _look_at(eye, target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), f=40.0, size=SIZE, name="") -> Camera:
    """OpenCV camera at ``eye`` looking at ``target`` (x right, y down, z forward)."""
    eye = np.asarray(eye, float)
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, -np.asarray(up, float))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    return Camera(K=K, R=R, t=-R @ eye, width=size, height=size, name=name)


def _sphere_masks(cameras, radius=1.0):
    """Exact masks of the ball of ``radius`` at the origin: pixel centres (i + 0.5, j + 0.5) whose ray
    meets it (written out here, independently of the evaluator's rays)."""
    masks = []
    for cam in cameras:
        j, i = np.mgrid[0:cam.height, 0:cam.width]
        x = (i.ravel() + 0.5 - cam.cx) / cam.fx
        y = (j.ravel() + 0.5 - cam.cy) / cam.fy
        d = np.stack([x, y, np.ones_like(x)], axis=1) @ cam.R  # camera -> world: Rᵀ d
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = np.broadcast_to(cam.center, d.shape)
        closest = o - np.sum(o * d, axis=1, keepdims=True) * d  # point of the line nearest the centre
        hit = (np.linalg.norm(closest, axis=1) <= radius) & (np.sum(-o * d, axis=1) > 0)
        masks.append(hit.reshape(cam.height, cam.width))
    return masks


def _scene(cameras, masks, normalisation=None) -> Scene:
    return Scene(name="toy", fmt="dtu", root=Path("."), cameras=cameras, images=[], masks=masks,
                 normalisation=normalisation or Normalisation())


@pytest.fixture(scope="module")
def ring():
    """Five cameras on a circle of radius 4 around the y axis, the exact unit-sphere masks."""
    angles = np.linspace(0, 2 * np.pi, 5, endpoint=False)
    cameras = [_look_at((4 * np.sin(a), 0.5, 4 * np.cos(a)), name=f"{k}") for k, a in enumerate(angles)]
    return cameras, _sphere_masks(cameras)


@pytest.fixture(scope="module")
def sphere():
    return trimesh.creation.icosphere(subdivisions=4, radius=1.0)


def test_exact_masks_give_high_iou_and_no_floaters(ring, sphere):
    cameras, masks = ring
    assert all(200 < m.sum() < SIZE * SIZE - 200 for m in masks)  # the sphere fills part of every view
    result = Silhouette().evaluate(sphere, _scene(cameras, masks))
    m = result["metrics"]
    assert m["mask_iou"] > 0.95 and m["mask_iou_min"] > 0.95
    assert m["outside_hull_area_share"] == 0.0
    diag = result["diagnostics"]
    assert len(diag["per_view_iou"]) == 5 and min(diag["per_view_iou"]) == pytest.approx(m["mask_iou_min"])
    assert diag["silhouette_pixels"][0] > 0 and "raycast" in diag["seconds"]
    assert result["protocol"]["hull_dilate_px"] == 1 and result["protocol"]["version"] == 1


def test_shifted_masks_give_a_much_lower_iou(ring, sphere):
    cameras, masks = ring
    shifted = [np.roll(m, 8, axis=1) for m in masks]
    m = Silhouette().evaluate(sphere, _scene(cameras, shifted))["metrics"]
    assert m["mask_iou"] < 0.6


def test_views_option_scores_only_those_views(ring, sphere):
    cameras, masks = ring
    bad = [m.copy() for m in masks]
    bad[2][:] = False
    result = Silhouette().evaluate(sphere, _scene(cameras, bad), views=(0, 1))
    assert result["metrics"]["mask_iou"] > 0.95 and result["diagnostics"]["views"] == [0, 1]
    assert Silhouette().evaluate(sphere, _scene(cameras, bad))["metrics"]["mask_iou_min"] == 0.0
    with pytest.raises(EvaluationError, match="view indices"):
        Silhouette().evaluate(sphere, _scene(cameras, masks), views=(7,))


def test_detached_cube_outside_the_hull_counts_with_its_area_share(ring, sphere):
    cameras, masks = ring
    cube = trimesh.creation.box(extents=(0.3, 0.3, 0.3))
    cube.apply_translation((0.0, 3.0, 0.0))  # above the sphere: outside every mask or every view
    both = trimesh.util.concatenate([sphere, cube])
    m = Silhouette().evaluate(both, _scene(cameras, masks))["metrics"]
    expected = cube.area / (cube.area + sphere.area)
    assert m["outside_hull_area_share"] == pytest.approx(expected, abs=1e-6)


def test_dataset_frame_input_is_mapped_to_the_cameras_frame(ring, sphere):
    cameras, masks = ring
    norm = Normalisation(scale=2.5, center=np.array([10.0, -3.0, 7.0]))
    in_dataset = trimesh.Trimesh(norm.apply(sphere.vertices), sphere.faces, process=False)
    scene = _scene(cameras, masks, norm)
    direct = Silhouette().evaluate(sphere, scene)["metrics"]
    mapped = Silhouette().evaluate(in_dataset, scene, frame="dataset")["metrics"]
    assert mapped["mask_iou"] == pytest.approx(direct["mask_iou"], abs=1e-3)
    # the dataset-frame mesh read as normalised is far off the object
    assert Silhouette().evaluate(in_dataset, scene)["metrics"]["mask_iou"] < 0.5


def test_pixel_centres_are_at_half_integers():
    """A plate whose projected edges lie a quarter pixel inside pixel boundaries 5 and 15: exactly pixels
    5..14 have their centre on it. Rays through (i, j) or (i + 1, j + 1) instead of (i + 0.5, j + 0.5)
    lose a row and a column (IoU 0.81)."""
    cam = Camera(K=np.array([[20.0, 0, 10], [0, 20.0, 10], [0, 0, 1]]), R=np.eye(3), t=np.array([0, 0, 2.0]),
                 width=20, height=20)
    # u = 20 x / 2 + 10: x = ±0.475 -> u = 5.25 and 14.75
    h = 0.475
    plate = trimesh.Trimesh([[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]], [[0, 1, 2], [0, 2, 3]], process=False)
    mask = np.zeros((20, 20), bool)
    mask[5:15, 5:15] = True
    result = Silhouette().evaluate(plate, _scene([cam], [mask]))
    assert result["metrics"]["mask_iou"] == 1.0
    assert result["diagnostics"]["silhouette_pixels"] == [100]
    moved = np.roll(mask, 1, axis=0)
    assert Silhouette().evaluate(plate, _scene([cam], [moved]))["metrics"]["mask_iou"] < 0.85


def test_masks_at_another_resolution_rescale_the_cameras(ring, sphere):
    cameras, _ = ring
    half = [cam.scaled(0.5) for cam in cameras]
    masks = _sphere_masks(half)
    m = Silhouette().evaluate(sphere, _scene(cameras, masks))["metrics"]
    assert m["mask_iou"] > 0.9 and m["outside_hull_area_share"] == 0.0


def test_empty_mesh_scores_zero_with_a_warning(ring, tmp_path):
    cameras, masks = ring
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int), process=False)
    path = tmp_path / "empty.ply"
    empty.export(path)
    for mesh in (empty, path):
        with pytest.warns(UserWarning, match="no faces"):
            result = Silhouette().evaluate(mesh, _scene(cameras, masks))
        assert result["metrics"] == {"mask_iou": 0.0, "mask_iou_min": 0.0, "outside_hull_area_share": 0.0}
        assert result["diagnostics"]["warnings"]


def test_scene_without_masks_is_a_clear_error(ring, sphere):
    cameras, masks = ring
    with pytest.raises(EvaluationError, match="scene 'toy' has no object masks.*fix"):
        Silhouette().validate(_scene(cameras, None))
    not_loaded = _scene(cameras, None)
    not_loaded.mask_paths = [Path(f"mask/{i:03d}.png") for i in range(len(cameras))]
    Silhouette().validate(not_loaded)  # masks on disk: the evaluator applies
    with pytest.raises(EvaluationError, match="load the scene's images"):
        Silhouette().evaluate(sphere, not_loaded)


def test_registered_with_its_needs():
    ev = get_evaluator("silhouette")
    assert isinstance(ev, Silhouette) and ev.needs == ("masks",) and ev.requires == ("mesh",)
    assert ev.metrics["mask_iou"].higher_is_better and not ev.metrics["outside_hull_area_share"].higher_is_better
