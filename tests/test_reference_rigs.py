"""The DTU-like and TnT-like scenes stand in the datasets' own rigs (docs/scenes.md): DTU's cameras exactly,
and a frame (fx/W, camera distance, depth × focal, scene radius, near plane) within 10% of the real captures'."""

import json

import numpy as np
import pytest
import trimesh

from gsbench.cli import main
from gsbench.data.dtu import PIXEL_SHIFT, decompose_projection, read_cameras_npz, write_cameras_npz
from gsbench.data.frame import NEAR_PLANE, cameras_extent, frame_quantities
from gsbench.data.loader import check_scene
from gsbench.data.meta import read_meta
from gsbench.data.reference_rigs import barn_rig, dtu_rig
from gsbench.data.similarity import decompose, similarity
from gsbench.data.synthetic.generator import RIGGED, SPECS, plan_frame, plan_scene
from gsbench.data.synthetic.make import make_mesh_scene, make_scene
from gsbench.errors import DataError
from gsbench.raster.types import RasterSettings

DTU_RIGGED = [f"synthetic/{name}" for name in RIGGED if name.startswith("dtu")]
TNT_RIGGED = [f"synthetic/{name}" for name in RIGGED if name.startswith("tnt")]


def test_near_plane_is_the_rasterizers():
    assert NEAR_PLANE == RasterSettings().near_plane


def test_reference_rigs_read_as_published():
    dtu, barn = dtu_rig(), barn_rig()
    assert len(dtu.cameras) == 49 and len(barn.cameras) == 410
    dtu_q, barn_q = frame_quantities(dtu.cameras, dtu.region), frame_quantities(barn.cameras, barn.region)
    # scan 65: fx = 2892.3 px on 1600 px, cameras 2.66-2.85 units from the sphere's centre
    assert dtu_q.fx_over_width == pytest.approx(1.8077, abs=1e-4) and dtu_q.camera_distance == pytest.approx(2.784, abs=1e-3)
    # Barn: fx = 1120 px on 1920 px; median camera 14.8 m (horizontally) from the crop centre, crop radius 11.98 m
    assert barn_q.fx_over_width == pytest.approx(1120 / 1920) and 1.2 < barn_q.camera_distance < 1.3
    # Barn's training frame is its COLMAP frame (metres / 4.139): crop radius 2.84, cameras' extent 5.28, near/D 0.057
    assert barn.region.radius / barn.region.training_scale == pytest.approx(2.843, abs=1e-3)
    assert cameras_extent(np.array([c.center for c in barn.training_cameras])) == pytest.approx(5.280, abs=1e-3)
    assert barn_q.near_over_depth == pytest.approx(0.057, abs=1e-3)


def test_dtu_rig_is_dtus_cameras_exactly(tmp_path):
    """Written out and read back as a loader reads cameras.npz, the scene's cameras are scan 65's
    (intrinsics and normalised centres to 1e-6)."""
    reference = dtu_rig().training_cameras
    plan = plan_scene("synthetic/dtu-rig-spot", res=1.0)
    scale_mat = similarity(plan.normalisation.scale, None, plan.normalisation.center)
    write_cameras_npz(tmp_path / "cameras.npz", plan.dataset_cameras, scale_mat)
    projections, _ = read_cameras_npz(tmp_path / "cameras.npz", len(reference))
    for projection, ref in zip(projections, reference):
        K, R, t = decompose_projection(projection)
        np.testing.assert_allclose(PIXEL_SHIFT @ K, ref.K, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(-R.T @ t, ref.center, atol=1e-6)


@pytest.mark.parametrize("name", DTU_RIGGED + TNT_RIGGED)
def test_frame_within_ten_percent_of_the_real_capture(name):
    reference = dtu_rig() if name in DTU_RIGGED else barn_rig()
    real = frame_quantities(reference.cameras, reference.region).as_dict()
    plan = plan_scene(name, res=(160, 120) if name in DTU_RIGGED else (192, 108))
    for key, value in plan_frame(plan).as_dict().items():
        assert value == pytest.approx(real[key], rel=0.10), (name, key, value, real[key])


@pytest.mark.parametrize("name", TNT_RIGGED)
def test_tnt_rig_scenes_colmap_frame_has_barns_scale(name):
    """In Barn's rig the GT -> COLMAP scale makes the crop radius Barn's in COLMAP units, so the scene's COLMAP
    frame (the training frame, data.tnt_frame: colmap) is Barn's: an absolute setting acts as on Barn. The TnT
    scenes they are made from keep their own COLMAP frames (their files are unchanged)."""
    barn = barn_rig()
    plan = plan_scene(name, res=(192, 108))
    q = plan_frame(plan)
    crop_radius = q.depth_focal / q.fx_over_width / q.camera_distance  # COLMAP units
    assert crop_radius == pytest.approx(barn.region.radius / barn.region.training_scale, rel=1e-6)
    extent = cameras_extent(np.array([c.center for c in plan.dataset_cameras]))
    assert extent == pytest.approx(cameras_extent(np.array([c.center for c in barn.training_cameras])), rel=0.02)
    old = "synthetic/" + RIGGED[name.split("/")[1]]
    old_scale = decompose(plan_scene(old, res=(192, 108)).gt_to_dataset)[0]
    assert old_scale == pytest.approx(SPECS[old].colmap_scale, rel=1e-12)


def test_old_dtu_scenes_are_not_in_dtus_frame():
    """What issue 64 measured: the first DTU-like scenes' lens and distance are not DTU's."""
    real = frame_quantities(dtu_rig().cameras, dtu_rig().region)
    old = plan_frame(plan_scene("synthetic/dtu-bunny", res=(160, 120)))
    assert old.fx_over_width < 0.7 * real.fx_over_width and old.depth_focal < 0.5 * real.depth_focal


def test_dtu_rig_framing_sets_the_object_size():
    small, large = (plan_scene("synthetic/dtu-rig-spot", res=(160, 120), framing=f) for f in ("small", "dtu"))
    size = [p.surface.radius * np.cbrt(np.linalg.det(p.obj_to_gt[:3, :3])) for p in (small, large)]
    assert size[0] < 0.7 * size[1]  # mm: the same cameras, a smaller object
    np.testing.assert_allclose([c.center for c in small.normalised_cameras], [c.center for c in large.normalised_cameras])
    with pytest.raises(DataError, match="unit sphere"):
        plan_scene("synthetic/dtu-rig-spot", res=(160, 120), framing=0.6)


def test_barn_rig_refuses_framing():
    with pytest.raises(DataError, match="framing"):
        plan_scene("synthetic/tnt-rig-spot", res=(192, 108), framing="dtu")


def test_scene_check_prints_the_frame(tmp_path):
    folder = make_scene("synthetic/tnt-rig-sky", out=tmp_path / "sky", res=(96, 54))
    report = check_scene(folder)
    real = frame_quantities(barn_rig().cameras, barn_rig().region).as_dict()
    assert report["ok"] and report["frame"]["fx_over_width"] == pytest.approx(real["fx_over_width"], rel=0.02)
    assert report["frame"]["camera_distance"] == pytest.approx(real["camera_distance"], rel=0.10)


@pytest.mark.slow
def test_dtu_rig_scene_ground_truth_scores_at_the_floor(tmp_path):
    """In DTU's rig the GT frame is DTU's world (its z is not up): the table plane and ObsMask still hold,
    so the exact mesh scores completeness at the 0.2 mm sampling floor and the table is cut off."""
    box = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(*(lambda b: (b.vertices, b.faces))(
        trimesh.creation.box(extents=(1.0, 0.6, 0.4))), max_edge=0.02))
    box.export(tmp_path / "box.off")
    folder = make_mesh_scene(tmp_path / "box.off", fmt="dtu", res=(64, 48), framing="small", out=tmp_path / "box")
    assert read_meta(folder)["rig"] == "dtu"
    result = tmp_path / "result.json"
    assert main(["eval", "--mesh", str(folder / "gt_mesh.ply"), "--scene", str(folder), "--frame", "dataset",
                 "--evaluator", "dtu_chamfer", "--out", str(result)]) == 0
    metrics = json.loads(result.read_text())["results"]["dtu_chamfer"]["metrics"]
    assert metrics["completeness"] < 0.12 and metrics["accuracy"] < 0.3
