"""normal_similarity (mesh NC, docs/evaluation.md §4.1) and rendered_normal_similarity (docs/evaluation.md §4.3)."""

import eval_fixtures as F
import numpy as np
import pytest
import trimesh

from gsbench.errors import EvaluationError
from gsbench.evaluators.normal_similarity import NormalSimilarity, rendered_normal_similarity


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return F.dtu_scene(F.make_dtu_gt(tmp_path_factory.mktemp("dtu_n")))


def test_sphere_against_pca_normals_is_consistent(scene):
    res = NormalSimilarity().evaluate(F.dtu_sphere_mesh(), scene, n_samples=30_000)
    m, d = res["metrics"], res["diagnostics"]
    assert m["normal_consistency"] > 0.999 and m["normal_consistency_gated"] > 0.999
    assert res["protocol"]["version"] == 2 and d["filtered"]
    assert d["gt_normals"].startswith("PCA") and d["accuracy_pairs_fraction"] == 1.0
    assert 0.5 < d["max_dist"] < 1.5  # 5 x the ~0.2 mm GT sample spacing
    again = NormalSimilarity().evaluate(F.dtu_sphere_mesh(), scene, n_samples=30_000)
    assert again["metrics"] == m


def test_noise_lowers_nc_and_gate_ignores_a_floater(scene, tmp_path):
    rng = np.random.default_rng(0)
    noisy = F.dtu_sphere_mesh(subdivisions=4)
    noisy.vertices += rng.normal(0, 0.3 / F.DTU_SCALE, noisy.vertices.shape)
    assert NormalSimilarity().evaluate(noisy, scene, n_samples=20_000)["metrics"]["normal_consistency"] < 0.97
    box = trimesh.creation.box(extents=[0.2, 0.2, 0.2])  # a floater 5 mm ... 10 mm from the sphere
    box.apply_translation([1.0, 0, 0])
    with_floater = trimesh.util.concatenate([F.dtu_sphere_mesh(), box])
    m = NormalSimilarity().evaluate(with_floater, scene, n_samples=30_000)["metrics"]
    assert m["normal_consistency_gated"] > 0.999 > m["normal_consistency"]


def _upper_half(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The faces of ``mesh`` whose centroid lies above its centre (z > 0)."""
    return trimesh.Trimesh(mesh.vertices, mesh.faces[mesh.triangles_center[:, 2] > 0], process=False)


def test_headline_counts_holes_and_the_plane_filter_drops_the_table(tmp_path):
    plane_scene = F.dtu_scene(F.make_dtu_gt(tmp_path / "plane", plane_z=F.DTU_CENTER[2]))  # GT above z = centre
    half = _upper_half(F.dtu_sphere_mesh())
    m = NormalSimilarity().evaluate(half, plane_scene, n_samples=20_000)["metrics"]
    assert m["normal_consistency"] > 0.999  # the GT below the plane is not scored, as in the Chamfer
    holed = NormalSimilarity().evaluate(half, F.dtu_scene(F.make_dtu_gt(tmp_path / "all")), n_samples=20_000)["metrics"]
    assert holed["normal_consistency"] < 0.98 < 0.999 < holed["normal_consistency_gated"]  # the hole counts ungated only


def test_obsmask_filters_the_prediction(tmp_path):
    scene = F.dtu_scene(F.make_dtu_gt(tmp_path / "obs", obs_lower_half=False))
    res = NormalSimilarity().evaluate(F.dtu_sphere_mesh(), scene, n_samples=20_000)
    assert 0.4 < res["diagnostics"]["pred_samples"] / 20_000 < 0.6  # the lower half is unobserved


def test_a_mesh_far_from_the_gt_everywhere_is_scored_ungated(scene):
    far = F.dtu_sphere_mesh(radius_mm=F.DTU_RADIUS + 3)  # 3 mm out everywhere, inside the box and the ObsMask
    with pytest.warns(UserWarning, match="gated metrics are undefined"):
        res = NormalSimilarity().evaluate(far, scene, n_samples=20_000)
    assert set(res["metrics"]) == {"normal_consistency", "normal_accuracy", "normal_completeness"}
    assert res["metrics"]["normal_consistency"] > 0.99  # concentric: the normals still agree
    assert res["diagnostics"]["accuracy_pairs_fraction"] == 0.0 and res["diagnostics"]["max_dist"] < 3


def test_gt_mesh_option_and_errors(scene, tmp_path):
    gt = tmp_path / "gt_mesh.ply"
    mesh = F.dtu_sphere_mesh(subdivisions=4)
    mesh.export(gt)
    m = NormalSimilarity().evaluate(mesh, scene, gt_mesh=str(gt), frame="dataset", n_samples=5_000, max_dist=0.1)
    assert m["metrics"]["normal_consistency"] > 0.999 and m["diagnostics"]["gt_normals"] == "mesh samples"
    with pytest.raises(EvaluationError, match="wrong frame or units"):
        NormalSimilarity().evaluate(mesh, scene, frame="dataset", n_samples=5_000)  # normalised mesh read as mm
    with pytest.raises(EvaluationError, match="wrong frame or units, or a mesh nowhere near"):  # nothing filtered
        NormalSimilarity().evaluate(mesh, scene, gt_mesh=str(gt), frame="dataset", n_samples=5_000, max_dist=1e-9)
    with pytest.raises(EvaluationError, match="not found: .*nope.ply"):
        NormalSimilarity().evaluate(mesh, scene, gt_mesh=str(tmp_path / "nope.ply"))


def test_rendered_normal_similarity():
    n = np.zeros((4, 5, 3))
    n[..., 2] = 1.0
    tilted = n.copy()
    tilted[:2, :, 0] = 1.0  # 45 degrees in the top two rows (unnormalised on purpose)
    mask = np.ones((4, 5), bool)
    assert rendered_normal_similarity(n, n) == pytest.approx(1.0)
    assert rendered_normal_similarity(tilted, n, mask) == pytest.approx((1 + np.sqrt(0.5)) / 2)
    mask[:2] = False
    assert rendered_normal_similarity(tilted, n, mask) == pytest.approx(1.0)
    with pytest.raises(EvaluationError):
        rendered_normal_similarity(n, n, np.zeros((4, 5), bool))
