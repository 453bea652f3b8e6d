"""mesh_stats: components, watertightness, dataset-frame area and counts of any mesh."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from gsbench.data.camera import Camera, Normalisation, Scene
from gsbench.evaluators.mesh_stats import MeshStats
from gsbench.evaluators.resolve import get_evaluator


def _scene(scale=1.0) -> Scene:
    cam = Camera(K=np.eye(3), R=np.eye(3), t=np.zeros(3), width=4, height=4)
    return Scene(name="toy", fmt="dtu", root=Path("."), cameras=[cam], images=[],
                 normalisation=Normalisation(scale=scale, center=np.array([100.0, 0.0, -50.0])))


def _two_spheres():
    a = trimesh.creation.icosphere(subdivisions=2, radius=0.5)
    b = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    b.apply_translation((2.0, 0.0, 0.0))
    return a, b, trimesh.util.concatenate([a, b])


def test_two_disjoint_spheres():
    a, b, both = _two_spheres()
    result = MeshStats().evaluate(both, _scene(2.5))
    m = result["metrics"]
    assert m["components"] == 2.0 and m["watertight"] == 1.0
    assert m["area"] == pytest.approx((a.area + b.area) * 2.5**2, rel=1e-9)
    assert m["vertices"] == len(both.vertices) and m["faces"] == len(both.faces)
    assert result["protocol"] == {"name": "mesh_stats", "version": 1, "frame": "normalised"}


def test_dataset_frame_area_is_not_rescaled():
    _, _, both = _two_spheres()
    norm = _scene(2.5).normalisation
    in_dataset = trimesh.Trimesh(norm.apply(both.vertices), both.faces, process=False)
    m = MeshStats().evaluate(in_dataset, _scene(2.5), frame="dataset")["metrics"]
    assert m["area"] == pytest.approx(both.area * 2.5**2, rel=1e-9)


def test_unshared_vertices_and_holes():
    """A sphere written one triangle at a time is still one closed component; a removed face opens it."""
    sphere = trimesh.creation.icosphere(subdivisions=1)
    soup = trimesh.Trimesh(sphere.vertices[sphere.faces].reshape(-1, 3),
                           np.arange(3 * len(sphere.faces)).reshape(-1, 3), process=False)
    m = MeshStats().evaluate(soup, _scene())["metrics"]
    assert m["components"] == 1.0 and m["watertight"] == 1.0 and m["vertices"] == 3 * len(sphere.faces)
    opened = trimesh.Trimesh(sphere.vertices, sphere.faces[1:], process=False)
    m = MeshStats().evaluate(opened, _scene())["metrics"]
    assert m["components"] == 1.0 and m["watertight"] == 0.0


def test_empty_mesh_gives_zeros_with_a_warning(tmp_path):
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int), process=False)
    path = tmp_path / "empty.ply"
    empty.export(path)
    for mesh in (empty, path):
        with pytest.warns(UserWarning, match="no faces"):
            result = MeshStats().evaluate(mesh, _scene())
        assert result["metrics"] == {"components": 0.0, "watertight": 0.0, "area": 0.0, "vertices": 0.0, "faces": 0.0}


def test_registered_and_applies_to_every_scene():
    ev = get_evaluator("mesh_stats")
    assert isinstance(ev, MeshStats) and ev.needs == () and ev.version == 1
    ev.validate(_scene())  # no ground truth, no masks: nothing to miss
    assert not ev.metrics["components"].higher_is_better and ev.metrics["watertight"].higher_is_better
    assert all(ev.metrics[m].higher_is_better is None for m in ("area", "vertices", "faces"))  # shown, never ranked
    assert ev.metrics["area"].unit == "units^2"
