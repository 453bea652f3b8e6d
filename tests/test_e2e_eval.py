"""End to end: a generated synthetic scene's exact surface, scored through `gsbench eval`, sits at the
protocol's floor; a displaced copy does not. This is the default-run end-to-end check of the
data -> evaluator path (the TnT variant is marked slow)."""

import json

import numpy as np
import pytest
import trimesh

from gsbench.cli import main


@pytest.fixture(scope="module")
def spot_dtu(tmp_path_factory):
    out = tmp_path_factory.mktemp("scenes") / "spot"
    assert main(["scene", "make", "synthetic/spot", "--res", "64", "48", "--out", str(out)]) == 0
    return out


def _eval(mesh, scene, tmp_path, *extra):
    result = tmp_path / "result.json"
    assert main(["eval", "--mesh", str(mesh), "--scene", str(scene), "--frame", "dataset", "--out", str(result),
                 *extra]) == 0
    return json.loads(result.read_text())["results"]


def test_exact_surface_scores_at_the_dtu_floor_and_a_shifted_one_does_not(spot_dtu, tmp_path):
    exact = _eval(spot_dtu / "gt_mesh.ply", spot_dtu, tmp_path)
    assert exact["dtu_chamfer"]["metrics"]["chamfer"] < 0.15  # 0.2 mm sampling floor
    assert exact["normal_similarity"]["metrics"]["normal_consistency"] > 0.99
    mesh = trimesh.load(spot_dtu / "gt_mesh.ply", process=False)
    mesh.vertices = mesh.vertices + np.array([1.0, 0.0, 0.0])  # 1 mm shift
    mesh.export(tmp_path / "shifted.ply")
    shifted = _eval(tmp_path / "shifted.ply", spot_dtu, tmp_path, "--evaluator", "dtu_chamfer")
    assert 0.4 < shifted["dtu_chamfer"]["metrics"]["chamfer"] < 1.0


@pytest.mark.slow
def test_exact_surface_scores_f1_one_on_tnt(tmp_path):
    scene = tmp_path / "spot-tnt"
    assert main(["scene", "make", "synthetic/spot-tnt", "--res", "96", "54", "--out", str(scene)]) == 0
    result = _eval(scene / "gt_mesh.ply", scene, tmp_path, "--evaluator", "tnt_f1")
    assert result["tnt_f1"]["metrics"]["f1"] > 0.99
