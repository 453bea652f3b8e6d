"""experiments/dtu_rig_units/scaled_world.py: a DTU scene's world scaled by s leaves what a method sees (the
normalised cameras) as it was and scales what the DTU protocol measures in millimetres by s."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
import trimesh

from gsbench.data.loader import load_scene
from gsbench.errors import DataError
from gsbench.evaluators.dtu_chamfer import DTUChamfer

SCRIPT = Path(__file__).resolve().parents[1] / "experiments" / "dtu_rig_units" / "scaled_world.py"
SCALE = 0.5
OFFSET_MM = 4.0  # the exact surface pushed out along its normals: Chamfer about this, in the scene's millimetres
PROTOCOL = {"frame": "normalised", "cull": "none", "sampled": False, "downsample_density": 1.0}  # coarse: seconds


@pytest.fixture(scope="module")
def scaled_world():
    spec = importlib.util.spec_from_file_location("scaled_world", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def scenes(tiny_spot, scaled_world, tmp_path_factory):
    out = tmp_path_factory.mktemp("scaled") / "spot-half"
    scaled_world.write_scaled_scene(Path(tiny_spot), out, SCALE)
    return load_scene(str(tiny_spot), load_images=False), load_scene(str(out), load_images=False)


def test_the_normalised_cameras_are_unchanged_and_the_millimetres_scaled(scenes):
    original, scaled = scenes
    for a, b in zip(original.cameras, scaled.cameras, strict=True):
        np.testing.assert_allclose(b.K, a.K, rtol=1e-9)
        np.testing.assert_allclose(b.R, a.R, atol=1e-9)
        np.testing.assert_allclose(b.t, a.t, atol=1e-9)
    assert scaled.normalisation.scale == pytest.approx(SCALE * original.normalisation.scale, rel=1e-9)
    np.testing.assert_allclose(scaled.normalisation.center, SCALE * original.normalisation.center, rtol=1e-9)


def test_the_dtu_chamfer_of_one_normalised_mesh_scales_with_the_world(scenes):
    original, scaled = scenes
    gt = trimesh.load(original.root / "gt_mesh.ply", process=False)
    pushed_mm = gt.vertices + OFFSET_MM * gt.vertex_normals
    mesh = trimesh.Trimesh(original.normalisation.invert(pushed_mm), gt.faces, process=False)  # what a method writes
    before = DTUChamfer().evaluate(mesh, original, **PROTOCOL)["metrics"]["chamfer"]
    after = DTUChamfer().evaluate(mesh, scaled, **PROTOCOL)["metrics"]["chamfer"]
    assert before == pytest.approx(OFFSET_MM, rel=0.1)
    assert after == pytest.approx(SCALE * before, rel=0.1)


def test_a_new_folder_only(tiny_spot, scaled_world, tmp_path):
    with pytest.raises(DataError, match="exists; fix: give a new folder"):
        scaled_world.write_scaled_scene(Path(tiny_spot), tmp_path, SCALE)
    with pytest.raises(DataError, match="must be positive"):
        scaled_world.write_scaled_scene(Path(tiny_spot), tmp_path / "new", 0.0)
