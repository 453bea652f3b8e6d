"""Synthetic scenes: generate tiny versions of the built-ins, load them back and check against the plan."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gsbench.data.frame import cameras_extent
from gsbench.data.loader import check_scene, load_scene
from gsbench.data.synthetic.generator import plan_scene
from gsbench.data.synthetic.make import make_scene
from gsbench.data.tnt import read_log
from gsbench.errors import DataError

DTU_RES, TNT_RES = (64, 48), (64, 36)
CASES = {  # key -> (built-in name, format, resolution)
    "dtu": ("synthetic/spot", "dtu", DTU_RES),
    "dtu-colmap": ("synthetic/spot", "dtu-colmap", DTU_RES),
    "tnt": ("synthetic/spot", "tnt", TNT_RES),
    "km": ("synthetic/spot-km", None, TNT_RES),
    "far": ("synthetic/spot-far", None, DTU_RES),
}


@pytest.fixture(scope="session")
def scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("synthetic")
    return {key: make_scene(name, fmt=fmt, out=root / key, res=res) for key, (name, fmt, res) in CASES.items()}


def _gt_points_normalised(scene, count=3000):
    """GT surface samples from the official GT files, mapped into the scene's normalised frame."""
    import open3d as o3d

    gt = scene.gt
    if gt.kind == "dtu":
        points = np.asarray(o3d.io.read_point_cloud(str(gt.root / "Points" / "stl" / f"stl{gt.scan:03d}_total.ply")).points)
    else:
        points = np.asarray(o3d.io.read_point_cloud(str(gt.root / f"{gt.name}.ply")).points)
        colmap_to_gt = np.loadtxt(gt.root / f"{gt.name}_trans.txt")
        gt_to_colmap = np.linalg.inv(colmap_to_gt)
        points = points @ gt_to_colmap[:3, :3].T + gt_to_colmap[:3, 3]
    points = points[np.random.default_rng(0).choice(len(points), count, replace=False)]
    return scene.normalisation.invert(points)


@pytest.mark.parametrize("key", ["dtu", "dtu-colmap", "tnt"])
def test_round_trip_reprojection(scenes, key):
    name, fmt, res = CASES[key]
    scene = load_scene(scenes[key], tnt_frame="extent")  # the generator's normalisation (plan.normalised_cameras)
    plan = plan_scene(name, fmt, res)
    assert scene.fmt == (fmt or plan.fmt) and len(scene.cameras) == len(plan.cameras)
    points = _gt_points_normalised(scene)
    errors = []
    for loaded, truth in zip(scene.cameras, plan.normalised_cameras):
        uv_l, z_l = loaded.project(points)
        uv_t, z_t = truth.project(points)
        assert np.all(z_t > 0) and np.allclose(z_l, z_t, rtol=1e-6)
        errors.append(np.linalg.norm(uv_l - uv_t, axis=1).mean())
    assert np.mean(errors) < 0.05
    for cam, img in zip(scene.cameras, scene.images):
        assert img.shape == (cam.height, cam.width, 3) and img.dtype == np.float32


@pytest.mark.parametrize("key", ["dtu", "tnt"])
def test_gt_points_project_into_object(scenes, key):
    """The GT files, the cameras and the rendered maps agree: GT points land on object pixels."""
    scene = load_scene(scenes[key])
    points = _gt_points_normalised(scene, 1000)
    inside = []
    for cam, name in zip(scene.cameras, scene.image_names):
        depth = np.load(scene.gt.depth_maps / name.replace(".png", ".npy"))
        ij = np.floor(cam.project(points)[0]).astype(int)
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < cam.width) & (ij[:, 1] >= 0) & (ij[:, 1] < cam.height)
        covered = np.zeros(len(points), bool)
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                i, j = np.clip(ij[:, 0] + di, 0, cam.width - 1), np.clip(ij[:, 1] + dj, 0, cam.height - 1)
                covered |= depth[j, i] > 0
        inside.append(covered[ok].mean())
    assert np.mean(inside) > 0.99


def test_masks_match_gt_depth_and_normals(scenes):
    scene = load_scene(scenes["dtu"])
    for cam, mask, name in zip(scene.cameras, scene.masks, scene.image_names):
        depth = np.load(scene.gt.depth_maps / name.replace(".png", ".npy"))
        normal = np.load(scene.gt.normal_maps / name.replace(".png", ".npy"))
        assert depth.dtype == np.float32 and normal.shape == depth.shape + (3,)
        assert np.mean(mask != (depth > 0)) < 1e-3
        j, i = np.nonzero(depth)
        n = normal[j, i]
        rays = np.stack([i + 0.5, j + 0.5, np.ones_like(i, float)], 1) @ np.linalg.inv(cam.K).T
        assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-4) and np.all(np.sum(n * rays, axis=1) <= 1e-6)


def test_depth_maps_match_cameras(scenes):
    """GT depth (the generator's normalised frame: a TnT scene's extent frame) equals the camera z of the surface
    point it shows."""
    scene = load_scene(scenes["tnt"], tnt_frame="extent")
    plan = plan_scene("synthetic/spot", "tnt", TNT_RES)
    cam = scene.cameras[5]
    depth = np.load(scene.gt.depth_maps / "000005.npy")
    j, i = np.nonzero(depth)
    rays = np.stack([i + 0.5, j + 0.5, np.ones_like(i, float)], 1) @ np.linalg.inv(cam.K).T
    world = (rays * depth[j, i, None] - cam.t) @ cam.R  # camera -> world
    obj = np.linalg.inv(plan.obj_to_dataset) @ scene.normalisation.to_dataset
    pts = world @ obj[:3, :3].T + obj[:3, 3]
    import open3d as o3d

    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(plan.surface.vertices.astype(np.float32)), o3d.core.Tensor(plan.surface.triangles.astype(np.uint32)))
    dist = rc.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy()
    assert np.max(dist) < 1e-4


def test_downscale_scales_cameras_and_images(scenes):
    full = load_scene(scenes["dtu"], load_images=False)
    half = load_scene(scenes["dtu"], downscale=2.0)
    assert half.images[0].shape == (24, 32, 3) and half.masks[0].shape == (24, 32)
    assert np.allclose(half.cameras[0].K, full.cameras[0].scaled(0.5).K)
    assert full.images == [] and full.masks is None


def test_dtu_gt_files_layout(scenes):
    import open3d as o3d
    from scipy.io import loadmat, whosmat

    scene = load_scene(scenes["dtu"])
    root, scan = scene.gt.root, scene.gt.scan
    assert scan == 1001
    stl = np.asarray(o3d.io.read_point_cloud(str(root / "Points" / "stl" / f"stl{scan:03d}_total.ply")).points)
    assert len(stl) > 100_000
    obs_file = root / "ObsMask" / f"ObsMask{scan}_10.mat"
    assert dict((n, c) for n, _, c in whosmat(obs_file))["ObsMask"] == "logical"
    obs = loadmat(obs_file)
    assert obs["ObsMask"].ndim == 3 and set(np.unique(obs["ObsMask"])) <= {0, 1}
    assert obs["BB"].shape == (2, 3) and obs["Res"].shape == (1, 1)
    # DTUeval-python indexing: most GT points fall in observed voxels, all inside the grid
    g = np.round((stl - obs["BB"][0]) / obs["Res"][0, 0]).astype(int)
    assert np.all(g >= 0) and np.all(g < obs["ObsMask"].shape)
    assert obs["ObsMask"][g[:, 0], g[:, 1], g[:, 2]].mean() > 0.99
    plane = loadmat(root / "ObsMask" / f"Plane{scan}.mat")["P"]
    assert plane.shape == (4, 1) and np.all(np.hstack([stl, np.ones((len(stl), 1))]) @ plane > 0)
    # the normalisation maps the normalised frame to DTU mm and the object fills the unit sphere
    radius = np.linalg.norm(scene.normalisation.invert(stl), axis=1).max()
    assert 0.8 < radius <= 1.0


def test_dtu_stl_holds_only_the_observed_surface(scenes):
    """Like a DTU scan, the stl samples the surface seen by >= 2 views; the unseen underside is left out."""
    import open3d as o3d

    from gsbench.data.similarity import decompose, transform_points
    from gsbench.data.synthetic.generator import DTU_GT_SPACING, DTU_MIN_VIEWS, TAU_FRACTION
    from gsbench.data.synthetic.groundtruth import sample_surface, visible_counts
    from gsbench.data.synthetic.render import Renderer

    name, fmt, res = CASES["dtu"]
    plan = plan_scene(name, fmt, res)
    scene = load_scene(scenes["dtu"], load_images=False)
    stl = np.asarray(o3d.io.read_point_cloud(str(scene.gt.root / "Points" / "stl" / f"stl{scene.gt.scan:03d}_total.ply")).points)
    whole = sample_surface(plan.surface, DTU_GT_SPACING / decompose(plan.obj_to_gt)[0], plan.seed)
    renderer = Renderer(plan.surface)
    depths = [renderer.render(cam).depth for cam in plan.cameras]
    seen = visible_counts(whole, plan.cameras, depths, tol=TAU_FRACTION) >= DTU_MIN_VIEWS
    assert 0 < seen.sum() < len(whole)
    assert np.allclose(stl, transform_points(plan.obj_to_gt, whole[seen]), atol=1e-6)


def test_tnt_gt_files_layout(scenes):
    import open3d as o3d

    scene = load_scene(scenes["tnt"])
    gt = scene.gt
    assert gt.kind == "tnt" and gt.name == "spot" and gt.tau == pytest.approx(0.0075)
    pcd = o3d.io.read_point_cloud(str(gt.root / f"{gt.name}.ply"))
    volume = o3d.visualization.read_selection_polygon_volume(str(gt.root / f"{gt.name}.json"))
    assert len(volume.crop_point_cloud(pcd).points) == len(pcd.points)
    assert json.loads((gt.root / f"{gt.name}.json").read_text())["class_name"] == "SelectionPolygonVolume"
    trans = np.loadtxt(gt.root / f"{gt.name}_trans.txt")
    assert trans.shape == (4, 4)
    poses = read_log(gt.root / f"{gt.name}_COLMAP_SfM.log")
    centres = scene.normalisation.apply(np.array([c.center for c in scene.cameras]))
    assert poses.shape == (len(scene.cameras), 4, 4) and np.allclose(poses[:, :3, 3], centres, atol=1e-9)


def test_tnt_frames_are_the_colmap_frame_and_its_division_by_the_extent(scenes):
    """``data.tnt_frame`` (docs/design.md §12.1): ``colmap`` keeps COLMAP's units about the cameras' centroid (the
    papers' frame: scale 1, settings' unit 1, the scene sphere the cameras' extent E); ``extent`` divides that by E.
    Both map back to the COLMAP frame of the reference trajectory."""
    colmap = load_scene(scenes["tnt"], load_images=False)
    extent = load_scene(scenes["tnt"], load_images=False, tnt_frame="extent")
    big_e = extent.normalisation.scale
    centres = np.array([c.center for c in colmap.cameras])
    assert (colmap.normalisation.scale, colmap.radius, extent.radius, extent.sphere) == (1.0, 1.0, 1.0, 1.0)
    assert colmap.sphere == pytest.approx(big_e) and cameras_extent(centres) == pytest.approx(big_e)
    np.testing.assert_allclose(centres.mean(axis=0), 0.0, atol=1e-9)
    extent_centres = np.array([c.center for c in extent.cameras])
    np.testing.assert_allclose(centres, big_e * extent_centres, atol=1e-9)
    np.testing.assert_allclose(colmap.points, big_e * extent.points, atol=1e-6)
    for a, b in zip(colmap.cameras, extent.cameras):
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)
        np.testing.assert_array_equal(a.K, b.K)
    poses = read_log(colmap.gt.root / f"{colmap.gt.name}_COLMAP_SfM.log")
    np.testing.assert_allclose(colmap.normalisation.apply(centres), poses[:, :3, 3], atol=1e-9)
    np.testing.assert_allclose(extent.normalisation.apply(extent_centres), poses[:, :3, 3], atol=1e-9)
    with pytest.raises(DataError, match="data.tnt_frame must be one of colmap, extent"):
        load_scene(scenes["tnt"], load_images=False, tnt_frame="nerfpp")


@pytest.mark.parametrize("key", ["km", "far"])
def test_hard_cases_are_normalised(scenes, key):
    scene = load_scene(scenes[key], load_images=False)
    points = _gt_points_normalised(scene)
    for cam in scene.cameras:
        assert all(np.all(np.isfinite(m)) for m in (cam.K, cam.R, cam.t))
    assert np.all(np.isfinite(points))
    centres = np.linalg.norm([c.center for c in scene.cameras], axis=1)
    if key == "km":  # TnT: COLMAP units about the cameras' centroid, every camera in the scene sphere; no huge offsets
        assert scene.gt.tau == pytest.approx(7.5) and 0.5 * scene.sphere < centres.max() <= scene.sphere / 1.1 + 1e-9
        assert np.abs(points).max() < scene.sphere
    else:  # DTU: the object is the unit sphere, cameras far away
        assert 0.8 < np.linalg.norm(points, axis=1).max() <= 1.0 and centres.min() > 8.0


def test_make_scene_skips_existing_and_check_reports(scenes):
    path = scenes["tnt"]
    stamp = (path / "gsbench_scene.json").stat().st_mtime_ns
    assert make_scene("spot", fmt="tnt", out=path, res=TNT_RES) == path
    assert (path / "gsbench_scene.json").stat().st_mtime_ns == stamp
    report = check_scene(path)
    assert report["ok"] and report["format"] == "tnt" and report["cameras"] == 48
    assert report["ground_truth"]["found"] and all(report["ground_truth"]["files"].values())


def test_supersample_one_renders_pixel_centres_only(tmp_path):
    """--supersample 1: one ray through each pixel centre (images differ only at edges and texture,
    depth is the same); the meta records it, the default meta does not (caches stay valid)."""
    import json

    import numpy as np
    from PIL import Image

    area = make_scene("synthetic/spot", out=tmp_path / "area", res=(48, 36))
    point = make_scene("synthetic/spot", out=tmp_path / "point", res=(48, 36), supersample=1)
    assert "supersample" not in json.loads((area / "gsbench_scene.json").read_text())
    assert json.loads((point / "gsbench_scene.json").read_text())["supersample"] == 1
    a = np.asarray(Image.open(area / "image" / "000000.png"), dtype=float)
    p = np.asarray(Image.open(point / "image" / "000000.png"), dtype=float)
    assert np.abs(a - p).max() > 20 and np.median(np.abs(a - p)) < 5
    np.testing.assert_array_equal(np.load(area / "gt_depth" / "000000.npy"), np.load(point / "gt_depth" / "000000.npy"))
