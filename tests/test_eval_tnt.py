"""tnt_f1 on an analytic TnT-layout fixture: a sphere, a known trans.txt, a ring trajectory (docs/evaluation.md §3)."""

import eval_fixtures as F
import numpy as np
import pytest

from gsbench.errors import EvaluationError
from gsbench.evaluators.tnt_f1 import SETS, TnTF1, precision_recall, tnt_gt_files

TAU = F.TNT_TAU
WORLD = F.similarity(0.7, [0, 1, 1], 1.1, [2.0, -1.0, 3.0])  # an arbitrary reconstruction frame


@pytest.fixture(scope="module")
def tnt_root(tmp_path_factory):
    return F.make_tnt_gt(tmp_path_factory.mktemp("tnt"))


@pytest.fixture(scope="module")
def scene(tnt_root):
    return F.tnt_scene(tnt_root)


@pytest.fixture(scope="module")
def exact(scene):
    return TnTF1().evaluate(F.tnt_sphere_mesh(), scene)


def test_scores_are_strict_threshold_fractions():
    grid = np.stack(np.meshgrid(np.arange(20.0), np.arange(20.0), [0.0]), -1).reshape(-1, 3)
    for dz, expected in [(0.0, 1.0), (0.99, 1.0), (1.0, 0.0), (1.5, 0.0)]:
        p, r, f = precision_recall(grid + [0, 0, dz], grid, tau=1.0)
        assert p == r == f == expected
    p, r, f = precision_recall(grid[:200], grid, tau=0.5)  # half the GT reconstructed
    assert (p, r, f) == (1.0, 0.5, pytest.approx(2 / 3))
    assert precision_recall(np.zeros((0, 3)), grid, 1.0) == (0.0, 0.0, 0.0)


def test_zero_offset_scores_one(exact):
    assert exact["metrics"] == {f"{m}{suffix}": 1.0 for m in ("precision", "recall", "f1") for suffix in SETS}
    d = exact["diagnostics"]
    assert d["stages"]["ransac"]["fitness"] == 1.0 and not d["suspect_alignment"]
    assert d["scale"] == pytest.approx(np.cbrt(np.linalg.det(F.TNT_TRANS[:3, :3])), rel=1e-3)
    assert d["crop_fraction"] == 1.0
    assert exact["protocol"]["tau"] == TAU and exact["protocol"]["icp_criteria"] == "official"
    assert exact["protocol"]["version"] == 2


def test_f1_falls_as_the_offset_passes_tau(scene):
    # +-offset by octant (sign of xyz), so no similarity can undo it; ICP can still fit one sign's
    # shell by rescaling, which caps the fall near 0.5 for offsets well beyond tau.
    f = {k: TnTF1().evaluate(F.tnt_sphere_mesh(k * TAU), scene)["metrics"]["f1"] for k in (0.5, 1.0, 2.0)}
    assert f[0.5] > 0.95
    assert f[1.0] < 0.6 and f[2.0] < 0.6


def test_similarity_is_realigned(scene, tnt_root, exact):
    rotated = TnTF1().evaluate(F.tnt_sphere_mesh(world=WORLD), F.tnt_scene(tnt_root, world=WORLD))
    assert rotated["metrics"]["f1"] == pytest.approx(exact["metrics"]["f1"], abs=1e-3)
    off = TAU  # the same defect scores the same in any frame
    a = TnTF1().evaluate(F.tnt_sphere_mesh(off), scene)["metrics"]["f1"]
    b = TnTF1().evaluate(F.tnt_sphere_mesh(off, world=WORLD), F.tnt_scene(tnt_root, world=WORLD))["metrics"]["f1"]
    assert b == pytest.approx(a, abs=0.02)


def test_deterministic(scene, exact):
    again = TnTF1().evaluate(F.tnt_sphere_mesh(), scene, icp_criteria="intended")
    assert again["metrics"]["f1"] > 0.99
    one = TnTF1().evaluate(F.tnt_sphere_mesh(0.7 * TAU), scene)
    two = TnTF1().evaluate(F.tnt_sphere_mesh(0.7 * TAU), scene)
    assert one["metrics"] == two["metrics"]
    assert one["diagnostics"]["transformation"] == two["diagnostics"]["transformation"]


def test_trajectory_length_mismatch(scene, tnt_root):
    short = F.tnt_scene(tnt_root)
    short.cameras = short.cameras[:-1]
    with pytest.raises(EvaluationError, match="19 cameras but .*_COLMAP_SfM.log has 20 poses"):
        TnTF1().evaluate(F.tnt_sphere_mesh(), short)


def test_mesh_far_outside_the_crop(scene):
    far = F.tnt_sphere_mesh()
    far.apply_translation([50.0, 0, 0])
    with pytest.raises(EvaluationError, match="inside the crop volume"):
        TnTF1().evaluate(far, scene)


@pytest.mark.parametrize("label", ["GT point cloud", "crop volume", "alignment", "reference trajectory"])
def test_missing_gt_file_is_named(tmp_path, label):
    scene = F.tnt_scene(tmp_path)
    files = tnt_gt_files(scene)
    for name, path in files.items():
        if name != label:
            path.touch()
    with pytest.raises(EvaluationError, match=files[label].name.replace(".", r"\.")):
        TnTF1().evaluate(F.tnt_sphere_mesh(), scene)
