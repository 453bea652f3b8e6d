"""What each protocol number depends on: the official DTU / TnT numbers move with the triangulation of
one surface, the area-sampled ones do not; TnT's three point sets; the capped TnT queries; the
toolbox's uniform downsampling rule; the two DTU mask-culling conventions."""

import eval_fixtures as F
import numpy as np
import pytest
import trimesh

from gsbench.evaluators import culling
from gsbench.evaluators.dtu_chamfer import DTUChamfer
from gsbench.evaluators.resolve import run_options
from gsbench.evaluators.tnt_f1 import TnTF1, precision_recall, uniform_rate


def fan(mesh: trimesh.Trimesh, k: int) -> trimesh.Trimesh:
    """The same surface with every triangle (a, b, c) cut into ``k`` slivers fanned from a over b -> c."""
    vertices, faces, n = [mesh.vertices], [], len(mesh.vertices)
    t = np.linspace(0, 1, k + 1)[1:-1, None]
    for a, b, c in mesh.faces:
        vertices.append(mesh.vertices[b] * (1 - t) + mesh.vertices[c] * t)
        ids = [b, *range(n, n + k - 1), c]
        n += k - 1
        faces += [[a, ids[i], ids[i + 1]] for i in range(k)]
    return trimesh.Trimesh(np.concatenate(vertices), np.array(faces), process=False)


def flat_subdivided(mesh: trimesh.Trimesh, times: int) -> trimesh.Trimesh:
    """The same surface, each triangle split into 4 at its edge midpoints ``times`` times."""
    for _ in range(times):
        mesh = mesh.subdivide()
    return mesh


@pytest.fixture(scope="module")
def dtu_scene(tmp_path_factory):
    return F.dtu_scene(F.make_dtu_gt(tmp_path_factory.mktemp("dtu_protocols")))


@pytest.fixture(scope="module")
def tnt_scene(tmp_path_factory):
    return F.tnt_scene(F.make_tnt_gt(tmp_path_factory.mktemp("tnt_protocols")))


def test_dtu_sampled_chamfer_ignores_the_triangulation(dtu_scene):
    coarse = F.dtu_sphere_mesh(subdivisions=3)  # ~3 mm triangles
    scores = {name: DTUChamfer().evaluate(mesh, dtu_scene, cull="none")["metrics"]
              for name, mesh in (("coarse", coarse), ("fan", fan(coarse, 20)), ("fine", flat_subdivided(coarse, 2)))}
    official = [s["chamfer"] for s in scores.values()]
    sampled = [s["chamfer_sampled"] for s in scores.values()]
    assert max(official) - min(official) > 0.04  # mm: the fan's slivers leave the official grid sparse
    assert max(sampled) - min(sampled) < 0.003
    assert all(s["accuracy_sampled"] > 0 and s["completeness_sampled"] > 0 for s in scores.values())


def test_dtu_sampled_off_leaves_the_official_numbers(dtu_scene):
    """``eval.dtu_sampled: false`` (the boards of large objects) skips the area samples and changes nothing else."""
    mesh = F.dtu_sphere_mesh(subdivisions=3)
    both = DTUChamfer().evaluate(mesh, dtu_scene, cull="none")
    official = DTUChamfer().evaluate(mesh, dtu_scene, cull="none", sampled=False)
    assert "chamfer_sampled" in both["metrics"] and not any(k.endswith("_sampled") for k in official["metrics"])
    assert official["metrics"] == {k: v for k, v in both["metrics"].items() if not k.endswith("_sampled")}
    assert run_options("2dgs", ["dtu_chamfer", "tnt_f1"], False) == {"dtu_chamfer": {"cull": "2dgs", "sampled": False}}


def test_tnt_point_sets_and_sampled_f1_ignore_the_triangulation(tnt_scene):
    coarse_mesh = F.tnt_sphere_mesh(subdivisions=3)  # vertices ~0.23 apart in GT units, tau 0.05
    coarse = TnTF1().evaluate(coarse_mesh, tnt_scene)["metrics"]
    fine = TnTF1().evaluate(flat_subdivided(coarse_mesh, 2), tnt_scene)["metrics"]
    assert coarse["f1"] < 0.5 < fine["f1"]  # official: vertices alone miss the GT between them
    assert coarse["f1"] < coarse["f1_centroids"] < coarse["f1_sampled"]
    assert coarse["f1_sampled"] == pytest.approx(fine["f1_sampled"], abs=0.01)
    assert fine["f1_sampled"] > 0.99


def test_capped_queries_give_the_same_fractions():
    rng = np.random.default_rng(0)
    target = rng.random((3000, 3))
    source = target[:1500] + rng.normal(0, 0.03, (1500, 3))  # a partial, noisy copy
    for tau in (0.01, 0.03, 0.1):
        assert precision_recall(source, target, tau) == precision_recall(source, target, tau, capped=False)


def test_uniform_downsampling_follows_the_toolbox_rate():
    assert uniform_rate(4_000_000, 4_000_000) == 1  # not above the cap: every point
    assert uniform_rate(5_000_000, 4_000_000) == 1  # round(1.25) = 1 (ceil would give 2)
    assert uniform_rate(7_000_000, 4_000_000) == 2
    assert uniform_rate(10_000_000, 4_000_000) == 2  # round half to even, as Python's round


def test_culling_conventions_differ_in_radius(dtu_scene):
    assert culling.dilation_radius(200, 24, 1600) == 3  # 2dgs: 24 px at 1600 px wide
    gof = culling.CULL_CONVENTIONS["gof"]
    assert culling.dilation_radius(200, gof.radius, gof.reference_width) == 6  # gof: 6 px at the masks' own size
    cam = dtu_scene.cameras[0]
    mask = np.zeros((cam.height, cam.width), bool)
    mask[:, : cam.width // 2] = True
    one_view = F.dtu_scene(dtu_scene.root, masks=[mask] + [np.ones_like(mask)] * (len(dtu_scene.cameras) - 1))
    # points on the principal row, in pixels 0..9 right of the mask's edge (at distance 1..10 px from it)
    offsets = np.arange(10)
    xs = cam.width // 2 + offsets + 0.5
    rays = np.stack([(xs - cam.K[0, 2]) / cam.K[0, 0], np.zeros_like(xs), np.ones_like(xs)], 1) * 3.0
    points = (rays - cam.t) @ cam.R  # camera -> world: R^T (x - t)
    kept = {name: culling.cull_mesh(points, None, one_view, name, "test", "normalised")[0]
            for name in ("2dgs", "gof", "none")}
    radius = {"2dgs": culling.dilation_radius(cam.width, 24, 1600), "gof": 6}  # 80 px wide: 1 and 6
    assert radius["2dgs"] == 1
    for name, r in radius.items():
        assert (kept[name] == (offsets + 1 <= r)).all(), name
    assert kept["none"].all()
    with pytest.raises(Exception, match="2dgs, gof|'2dgs', 'gof'"):
        culling.check_cull("wide")
