"""dtu_chamfer on an analytic DTU-layout fixture: a 20 mm sphere sampled at 0.2 mm (docs/evaluation.md §2)."""

import eval_fixtures as F
import numpy as np
import pytest
import trimesh

from gsbench.errors import EvaluationError
from gsbench.evaluators import pointsets
from gsbench.evaluators.geometry import to_dataset_frame
from gsbench.evaluators.dtu_chamfer import SAMPLE_BYTES, DTUChamfer, dtu_gt_files, sample_limit

# Sampling floor: mean NN distance to points ~0.2 mm apart is ~0.38 x spacing (hexagonal packing);
# completeness is a little larger because the greedy 0.2 mm downsampling leaves gaps up to 0.4 mm.
FLOOR = 0.15


@pytest.fixture(scope="module")
def dtu_root(tmp_path_factory):
    return F.make_dtu_gt(tmp_path_factory.mktemp("dtu"))


@pytest.fixture(scope="module")
def scene(dtu_root):
    return F.dtu_scene(dtu_root)


@pytest.fixture(scope="module")
def exact(scene):
    return DTUChamfer().evaluate(F.dtu_sphere_mesh(), scene)


def _upper_half(mesh, z=0.0):
    keep = mesh.vertices[mesh.faces].mean(axis=1)[:, 2] > z
    m = trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)
    m.remove_unreferenced_vertices()
    return m


def test_identical_surface_is_at_the_sampling_floor(exact):
    m = exact["metrics"]
    assert 0.0 < m["accuracy"] < FLOOR and 0.0 < m["completeness"] < FLOOR
    assert m["chamfer"] == pytest.approx((m["accuracy"] + m["completeness"]) / 2)
    d = exact["diagnostics"]
    assert d["culled_vertices"] == 0 and d["in_box_fraction"] == 1.0 and d["warnings"] == []
    expected = {"name": "dtu_chamfer", "version": 1, "downsample_density": 0.2, "patch_size": 60, "max_dist": 20,
                "seed": 0, "cull": "2dgs"}
    assert expected.items() <= exact["protocol"].items()


def test_radial_offset_of_half_a_millimetre(scene):
    m = DTUChamfer().evaluate(F.dtu_sphere_mesh(F.DTU_RADIUS + 0.5), scene)["metrics"]
    assert m["accuracy"] == pytest.approx(0.5, abs=0.05)
    assert m["completeness"] == pytest.approx(0.5, abs=0.05)


def test_hemisphere_is_accurate_but_incomplete(scene):
    m = DTUChamfer().evaluate(_upper_half(F.dtu_sphere_mesh()), scene)["metrics"]
    assert m["accuracy"] < FLOOR
    assert m["completeness"] > 3.0  # lower-half GT points up to 20 mm away (farther ones dropped)


def test_plane_filter(tmp_path):
    # Plane through the centre: only GT points above it count for completeness -> a hemisphere is complete.
    scene = F.dtu_scene(F.make_dtu_gt(tmp_path, plane_z=F.DTU_CENTER[2]))
    hemi = DTUChamfer().evaluate(_upper_half(F.dtu_sphere_mesh()), scene)["metrics"]
    assert hemi["completeness"] < FLOOR


def test_obsmask_limits_accuracy_but_not_completeness(tmp_path, scene):
    # ObsMask cleared below the centre: a floater there does not count for accuracy, and completeness
    # of the lower GT uses the box-filtered (not ObsMask-filtered) lower half of the mesh.
    floater = trimesh.creation.icosphere(3, radius=3 / F.DTU_SCALE)
    floater.apply_translation(np.array([24.0, 0, -10]) / F.DTU_SCALE)
    both = trimesh.util.concatenate([F.dtu_sphere_mesh(), floater])
    masked = DTUChamfer().evaluate(both, F.dtu_scene(F.make_dtu_gt(tmp_path, obs_lower_half=False)))["metrics"]
    assert masked["accuracy"] < FLOOR and masked["completeness"] < FLOOR
    full_obs = DTUChamfer().evaluate(both, scene)["metrics"]
    assert full_obs["accuracy"] > masked["accuracy"] + 0.05


def test_deterministic_and_seeded(scene, exact):
    again = DTUChamfer().evaluate(F.dtu_sphere_mesh(), scene)
    assert again["metrics"] == exact["metrics"]
    other = DTUChamfer().evaluate(F.dtu_sphere_mesh(), scene, seed=1)["metrics"]
    assert other["accuracy"] == pytest.approx(exact["metrics"]["accuracy"], abs=0.01)


def test_pcd_mode_gt_frame_and_vis(scene, dtu_root, tmp_path):
    pts = F.fibonacci_sphere(120_000, F.DTU_RADIUS, F.DTU_CENTER)
    res = DTUChamfer().evaluate(pts, scene, mode="pcd", frame="dataset", cull="none", vis_dir=str(tmp_path))
    assert res["metrics"]["accuracy"] < FLOOR and res["metrics"]["completeness"] < FLOOR
    assert all((tmp_path / f"vis_{F.DTU_SCAN:03d}_{k}.ply").is_file() for k in ("d2s", "s2d"))


def test_culling_with_empty_masks_removes_everything(dtu_root):
    scene = F.dtu_scene(dtu_root, masks=[np.zeros((60, 80), bool)] * 8)
    with pytest.raises(EvaluationError, match="culling removed every vertex"):
        DTUChamfer().evaluate(F.dtu_sphere_mesh(), scene)


def test_wrong_units_warns_then_fails_before_allocating(scene):
    big = F.dtu_sphere_mesh()
    big.apply_scale(1000.0)  # metres read as millimetres
    with pytest.warns(UserWarning, match="wrong units or frame"):
        with pytest.raises(EvaluationError, match="samples at density 0.2.*wrong units"):
            DTUChamfer().evaluate(big, scene, cull="none")


def test_sample_limit_is_what_memory_holds_unless_set(scene):
    """A Poisson surface closed around the background (SuGaR on dtu-rig-spot: 3.2e6 mm², ~80 M samples) is the
    method's output, not wrong units: only the memory available bounds its samples."""
    assert sample_limit(None, available=1000 * SAMPLE_BYTES + SAMPLE_BYTES - 1) == 1000
    assert sample_limit(12, available=10**12) == 12
    with pytest.raises(EvaluationError, match="limit 1,000\\).*larger than the object"):
        DTUChamfer().evaluate(F.dtu_sphere_mesh(), scene, cull="none", max_sample_points=1000)


def test_area_samples_over_the_limit_fail_before_the_official_steps(scene, monkeypatch):
    """The area-sampled variant draws 4 samples per 0.2 mm square, more than the official grid: a mesh whose grid
    fits but whose area samples do not fails before the official steps run (not after them)."""
    mesh = F.dtu_sphere_mesh()
    grid = pointsets.barycentric_grid_bound(to_dataset_frame(np.asarray(mesh.vertices), scene, "normalised"),
                                            np.asarray(mesh.faces), 0.2)
    monkeypatch.setattr(pointsets, "greedy_downsample", lambda *a, **k: pytest.fail("the official steps ran"))
    with pytest.raises(EvaluationError, match="area samples at spacing 0.2"):
        DTUChamfer().evaluate(mesh, scene, cull="none", max_sample_points=grid + len(mesh.vertices))


def test_wrong_frame_warns_then_names_the_obsmask(scene):
    with pytest.warns(UserWarning, match="0.0% of the vertices"):
        with pytest.raises(EvaluationError, match=r"ObsMask7_10\.mat"):
            DTUChamfer().evaluate(F.dtu_sphere_mesh(), scene, frame="dataset", cull="none")


def test_bad_meshes(scene, tmp_path):
    with pytest.raises(EvaluationError, match="empty"):
        DTUChamfer().evaluate(trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), int)), scene)
    nan = F.dtu_sphere_mesh(subdivisions=1)
    v = nan.vertices.copy()
    v[3] = np.nan
    path = tmp_path / "nan_mesh.ply"
    trimesh.Trimesh(v, nan.faces, process=False).export(path)
    with pytest.raises(EvaluationError, match="nan_mesh.ply.*NaN"):
        DTUChamfer().evaluate(path, scene)
    with pytest.raises(EvaluationError, match="not found: .*missing.ply"):
        DTUChamfer().evaluate(tmp_path / "missing.ply", scene)
    with pytest.raises(EvaluationError, match="no faces"):
        DTUChamfer().evaluate(np.zeros((5, 3)), scene)
    with pytest.raises(EvaluationError, match="unknown option"):
        DTUChamfer().evaluate(nan, scene, densty=0.2)


@pytest.mark.parametrize("label", ["STL points", "ObsMask", "Plane"])
def test_missing_gt_file_is_named(tmp_path, label):
    scene = F.dtu_scene(tmp_path)
    files = dtu_gt_files(scene)
    for name, path in files.items():
        if name != label:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.touch()
    with pytest.raises(EvaluationError, match=f"{label} \\({files[label]}\\)".replace(".", r"\.")):
        DTUChamfer().validate(scene)


def _sequential_reference(mesh_mm, root, seed=0):
    """docs/evaluation.md §2.2 written as plain loops (per triangle, per point), with a seeded shuffle."""
    import scipy.io
    from scipy.spatial import cKDTree

    from gsbench.evaluators.gt_io import read_points

    v, f = np.asarray(mesh_mm.vertices), np.asarray(mesh_mm.faces)
    samples = F.grid_samples_loop(v, f, 0.2)  # DTU's sampling density 0.2 mm
    data = np.concatenate([v, samples])
    data = data[np.random.default_rng(seed).permutation(len(data))]
    keep = np.ones(len(data), bool)
    for i, nb in enumerate(cKDTree(data).query_ball_point(data, 0.2)):
        if keep[i]:
            keep[nb] = False
            keep[i] = True
    down = data[keep]
    obs = scipy.io.loadmat(root / "ObsMask" / f"ObsMask{F.DTU_SCAN}_10.mat")
    mask, bb, res = obs["ObsMask"], obs["BB"], obs["Res"]
    data_in = down[np.all(down >= bb[0] - 60, axis=1) & np.all(down < bb[1] + 120, axis=1)]
    g = np.around((data_in - bb[0]) / res).astype(np.int32)
    ok = np.all((g >= 0) & (g < np.array(mask.shape)), axis=1)
    in_obs = data_in[ok][mask[g[ok][:, 0], g[ok][:, 1], g[ok][:, 2]].astype(bool)]
    stl = read_points(root / "Points" / "stl" / f"stl{F.DTU_SCAN:03d}_total.ply")
    d2s = cKDTree(stl).query(in_obs)[0]
    plane = scipy.io.loadmat(root / "ObsMask" / f"Plane{F.DTU_SCAN}.mat")["P"]
    above = stl[(np.c_[stl, np.ones(len(stl))] @ plane).ravel() > 0]
    s2d = cKDTree(data_in).query(above)[0]
    return d2s[d2s < 20].mean(), s2d[s2d < 20].mean()


def test_matches_a_sequential_implementation_bit_for_bit(tmp_path):
    root = F.make_dtu_gt(tmp_path, plane_z=F.DTU_CENTER[2] - 10, obs_lower_half=False)
    mesh = F.dtu_sphere_mesh(F.DTU_RADIUS + 0.3, subdivisions=3)
    got = DTUChamfer().evaluate(mesh, F.dtu_scene(root), cull="none")["metrics"]
    mm = trimesh.Trimesh(mesh.vertices * F.DTU_SCALE + F.DTU_CENTER, mesh.faces, process=False)
    acc, comp = _sequential_reference(mm, root)
    assert (got["accuracy"], got["completeness"]) == (acc, comp)
