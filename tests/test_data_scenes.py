"""DTU-like and TnT-like built-in scenes (an object in its environment): generate tiny versions, load
them back and check images, masks and GT files against the plan."""

from __future__ import annotations

import hashlib
import shutil

import numpy as np
import pytest
from PIL import Image

from gsbench.data.loader import check_scene, load_scene
from gsbench.data.similarity import transform_points
from gsbench.data.synthetic.builtin import BUILTIN_SCENES
from gsbench.data.synthetic.generator import DTU_PLANE_ABOVE_TABLE, SCAN_BASE, plan_scene
from gsbench.data.synthetic.make import make_scene

DTU_SCENES = ["dtu-spot", "dtu-stool", "dtu-bowl", "dtu-blocks", "dtu-fine", "dtu-plain", "dtu-bunny", "dtu-face",
              "dtu-glass-orb", "dtu-glass-wine", "dtu-glass-bottle", "dtu-glass-orb-opaque",
              "dtu-spot-near"]
OPEN_SCANS = ["dtu-face"]  # a range scan: an open sheet, no inside
TNT_SCENES = ["tnt-spot", "tnt-yard", "tnt-sky"]
DTU_RES, TNT_RES = (64, 48), (96, 54)


def _res(name):
    return DTU_RES if name.startswith("dtu") else TNT_RES


@pytest.fixture(scope="session")
def scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("scenes")
    return {name: make_scene(f"synthetic/{name}", out=root / name, res=_res(name)) for name in DTU_SCENES + TNT_SCENES}


def _plan(name):
    return plan_scene(f"synthetic/{name}", None, _res(name))


def _read_points(path):
    import open3d as o3d

    return np.asarray(o3d.io.read_point_cloud(str(path)).points)


def _object_depths(plan, cam):
    """Pixel-centre depth (object frame, camera z) of the object alone; inf where the ray misses it."""
    import open3d as o3d

    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.core.Tensor(plan.surface.vertices.astype(np.float32)), o3d.core.Tensor(plan.surface.triangles.astype(np.uint32)))
    jj, ii = np.mgrid[0:cam.height, 0:cam.width].astype(np.float64)
    dirs = np.stack([ii + 0.5, jj + 0.5, np.ones_like(ii)], -1) @ (cam.R.T @ np.linalg.inv(cam.K)).T
    rays = np.concatenate([np.broadcast_to(cam.center, dirs.shape), dirs], -1).astype(np.float32)
    return rc.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()


def test_new_scenes_are_listed_after_the_old_ones():
    names = list(BUILTIN_SCENES)
    assert names[:6] == ["synthetic/spot", "synthetic/spot-tnt", "synthetic/thin-plate", "synthetic/textureless",
                         "synthetic/spot-far", "synthetic/spot-km"]
    assert all(f"synthetic/{n}" in names for n in DTU_SCENES + TNT_SCENES)


@pytest.mark.parametrize("name", DTU_SCENES + TNT_SCENES)
def test_scene_loads_with_its_gt(scenes, name):
    report = check_scene(scenes[name])
    assert report["ok"], report
    scene = load_scene(scenes[name])
    dtu = name.startswith("dtu")
    assert scene.fmt == ("dtu-colmap" if dtu else "tnt") and scene.gt.kind == ("dtu" if dtu else "tnt")
    assert (scenes[name] / "gt_mesh.ply").is_file() and (scenes[name] / "gt_scene_mesh.ply").is_file()
    if dtu:
        assert scene.gt.scan == SCAN_BASE + list(BUILTIN_SCENES).index(f"synthetic/{name}")
    # SfM-like points cover what the images show: the object (inside the unit sphere) and the surroundings
    norm = np.linalg.norm(scene.points, axis=1)
    assert 20_000 <= len(scene.points) <= 30_000 and np.all(np.isfinite(scene.points))
    if dtu:
        assert np.mean(norm < 1.0) > 0.03 and np.mean(norm > 1.5) > 0.2  # framed as DTU: 0.27 on dtu-face


@pytest.mark.parametrize("name", DTU_SCENES)
def test_dtu_gt_files(scenes, name):
    """stl = object + table disk, all inside ObsMask; the Plane keeps the object and drops the table."""
    from scipy.io import loadmat, whosmat

    plan, root = _plan(name), scenes[name]
    scan = plan.scan
    stl = _read_points(root / "Points" / "stl" / f"stl{scan:03d}_total.ply")
    obs_file = root / "ObsMask" / f"ObsMask{scan}_10.mat"
    assert dict((n, c) for n, _, c in whosmat(obs_file))["ObsMask"] == "logical"
    obs = loadmat(obs_file)
    assert obs["BB"].shape == (2, 3) and obs["Res"].shape == (1, 1)
    g = np.round((stl - obs["BB"][0]) / obs["Res"][0, 0]).astype(int)
    assert np.all(g >= 0) and np.all(g < obs["ObsMask"].shape) and np.all(obs["ObsMask"][g[:, 0], g[:, 1], g[:, 2]])
    top = transform_points(plan.obj_to_gt, np.array([[0.0, 0.0, plan.world.ground_z]]))[0, 2]
    table = np.abs(stl[:, 2] - top) < 1e-6
    assert 50_000 < table.sum() < len(stl) - 50_000  # both the table and the object are scanned
    axis = transform_points(plan.obj_to_gt, np.zeros((1, 3)))[0, :2]
    reach = np.linalg.norm(stl[table, :2] - axis, axis=1)
    assert 75.0 < reach.max() <= 80.0 + 1e-6  # the table disk of radius 0.8 x 100 mm
    P = loadmat(root / "ObsMask" / f"Plane{scan}.mat")["P"]
    assert P.shape == (4, 1) and np.allclose(P[:3, 0], [0, 0, 1])
    above = np.hstack([stl, np.ones((len(stl), 1))]) @ P[:, 0] > 0
    assert not above[table].any()
    assert above[~table].mean() > 0.97 and np.all(above[stl[:, 2] > top + DTU_PLANE_ABOVE_TABLE + 1e-6])


@pytest.mark.parametrize("name", DTU_SCENES)
def test_masks_are_the_object_and_images_full(scenes, name):
    """Mask = the pixel-centre ray's first hit is the object; elsewhere the table or the room is seen."""
    plan = _plan(name)
    scene = load_scene(scenes[name])
    for k in (0, 17, 40):
        cam, mask, image = plan.cameras[k], scene.masks[k], scene.images[k]
        depth = np.load(scene.gt.depth_maps / f"{k:06d}.npy") / plan.depth_scale
        assert np.all(depth > 0)  # the room closes every view
        obj = _object_depths(plan, cam)
        first_is_object = np.abs(obj - depth) < 1e-4 * np.maximum(depth, 1.0)
        assert np.mean(mask != first_is_object) < 2e-3 and 0.01 < mask.mean() < 0.6
        black = np.all(image == 0, axis=-1)
        assert black.mean() < 0.01 and not black[~mask].any()


@pytest.mark.parametrize("name", DTU_SCENES + TNT_SCENES)
def test_object_meshes_are_closed_and_stand_on_the_ground(scenes, name):
    import trimesh

    plan = _plan(name)
    assert plan.surface.vertices[:, 2].min() == plan.world.ground_z
    mesh = trimesh.Trimesh(plan.surface.vertices, plan.surface.triangles, process=True)
    if name in OPEN_SCANS:
        assert not mesh.is_watertight and plan.mesh_info["watertight"] is False
        assert len(mesh.split(only_watertight=False)) == 1  # its largest part only
        return
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    if name != "tnt-yard":  # the yard's object is several separate blocks
        assert len(mesh.split(only_watertight=False)) == 1
    assert plan.surface.vertices[:, 2].min() == plan.world.ground_z
    written = trimesh.load(scenes[name] / "gt_mesh.ply", process=True)
    assert written.is_watertight and written.volume > 0


@pytest.mark.parametrize("name", TNT_SCENES)
def test_tnt_gt_files(scenes, name):
    """GT = object + ground inside the crop; the crop holds the GT and none of the props or the backdrop."""
    import open3d as o3d

    from gsbench.data.tnt import read_log

    plan, root = _plan(name), scenes[name]
    scene = load_scene(root, load_images=False)
    assert scene.gt.name == name and scene.gt.tau == pytest.approx(plan.tau)
    gt = _read_points(root / f"{name}.ply")
    volume = o3d.visualization.read_selection_polygon_volume(str(root / f"{name}.json"))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(gt))
    assert len(volume.crop_point_cloud(pcd).points) == len(gt)
    ground = transform_points(plan.obj_to_gt, np.array([[0.0, 0.0, plan.world.ground_z]]))[0, 2]
    on_ground = np.abs(gt[:, 2] - ground) < 1e-6 * max(1.0, abs(ground))
    assert 0.2 < on_ground.mean() < 0.95
    for part in plan.world.parts[1:]:
        if part.role in ("prop", "backdrop"):
            pts = transform_points(plan.obj_to_gt, part.vertices)
            inside = volume.crop_point_cloud(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)))
            assert len(inside.points) == 0, part.name
    if name == "tnt-sky":
        dome = next(p for p in plan.world.parts if p.name == "sky")
        size = np.ptp(plan.surface.vertices, axis=0).max()
        assert np.linalg.norm(dome.vertices[:, :2], axis=1).max() >= 50 * size
    trans = np.loadtxt(root / f"{name}_trans.txt")
    assert trans.shape == (4, 4)
    poses = read_log(root / f"{name}_COLMAP_SfM.log")
    assert poses.shape == (len(scene.cameras), 4, 4)
    images = load_scene(root).images
    assert max(np.mean(np.all(im == 0, axis=-1)) for im in images) < 0.01


def _digest(folder):
    return {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("name", ["dtu-fine", "tnt-sky"])
def test_generation_is_deterministic(scenes, tmp_path, name):
    again = make_scene(f"synthetic/{name}", out=tmp_path / name, res=_res(name))
    assert _digest(again) == _digest(scenes[name])
    shutil.rmtree(again)


def test_existing_scene_unchanged(tmp_path):
    """synthetic/spot at 80x60 gives the image, mask and stl bytes it gave before the environments were
    added. The float files (depth, cameras) are compared by value, not by bytes: numpy's and open3d's float
    code paths depend on the CPU's vector units, and their byte hashes from an AMD EPYC VM did not match on
    an Intel Xeon VM; which pixels hit is the same everywhere (the mask's bytes are). Their reference values
    were measured on the Intel Xeon VM; the tolerances allow last-bit differences, not a changed scene."""
    root = make_scene("synthetic/spot", out=tmp_path / "spot", res=(80, 60))
    digest = _digest(root)
    assert digest["image/000000.png"] == "77cae19b828855ab4b8f29194449d333c475c4aa60e777ae954b5197525df88c"
    assert digest["mask/000.png"] == "f5bbdded699c20753751aef6a3fe358213f5f1465ced514acc1ea01e213d3170"
    depth = np.load(root / "gt_depth" / "000000.npy").astype(np.float64)
    mask = np.asarray(Image.open(root / "mask" / "000.png"))[..., 0] > 0
    assert np.array_equal(depth > 0, mask) and mask.sum() == 462
    assert depth.sum() == pytest.approx(1225.184134, rel=1e-5)
    assert (depth**2).sum() == pytest.approx(3285.738497, rel=1e-5)
    assert digest["Points/stl/stl1001_total.ply"] == "016810491c93cc0f553d0e4312f5d4c0462e5b3f361ae411b390aeb0a7253573"
    cameras = np.load(root / "cameras.npz")
    world = np.stack([cameras[f"world_mat_{i}"] for i in range(49)]).astype(np.float64)
    assert len(cameras.files) == 2 * 49
    assert world.sum() == pytest.approx(3992593.845687, rel=1e-9)
    assert (world**2).sum() == pytest.approx(191971049813.0067, rel=1e-9)
    assert cameras["scale_mat_0"].sum() == pytest.approx(819.3119556, rel=1e-9)
