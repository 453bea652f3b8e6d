"""Scenes from mesh files (`gsbench scene make --mesh`) and framing: a known surface made into a scene
has ground truth the official evaluators score at the sampling floor and that lies on that surface; broken
files fail in one line before anything heavy; repairs are recorded; colours and axes come through;
framing gives the share it was asked for, and `gsbench list` states each built-in's share."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import trimesh
from PIL import Image

from gsbench.cli import main
from gsbench.data.loader import load_scene
from gsbench.data.meta import read_meta
from gsbench.data.synthetic.builtin import BUILTIN_SCENES
from gsbench.data.synthetic.framing import FRAMINGS, object_share, parse_framing
from gsbench.data.synthetic.generator import plan_from_meta, plan_scene
from gsbench.data.synthetic.make import make_mesh_scene
from gsbench.data.synthetic.mesh_file import read_mesh_object, up_rotation
from gsbench.data.synthetic.render import Renderer
from gsbench.errors import DataError

RES = (64, 48)


@pytest.fixture(scope="module")
def sphere_scene(tmp_path_factory):
    """An icosphere (radius 1, vertex colours) as a DTU-like scene framed as DTU on the synthetic cap rig: 100 mm
    across, its GT frame z up (DTU's own rig, the default, sizes the object instead: tests/test_reference_rigs.py)."""
    folder = tmp_path_factory.mktemp("mesh")
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    sphere.visual.vertex_colors = np.column_stack([(sphere.vertices * 0.4 + 0.5) * 255, np.full(len(sphere.vertices), 255)])
    sphere.export(folder / "ball.ply")
    return make_mesh_scene(folder / "ball.ply", out=folder / "ball", res=RES, rig="cap"), sphere


def _eval(mesh, scene, tmp_path, *extra):
    result = tmp_path / "result.json"
    assert main(["eval", "--mesh", str(mesh), "--scene", str(scene), "--frame", "dataset", "--out", str(result), *extra]) == 0
    return json.loads(result.read_text())["results"]


def test_sphere_ground_truth_lies_on_the_sphere_and_scores_at_the_floor(sphere_scene, tmp_path):
    root, sphere = sphere_scene
    meta = read_meta(root)
    assert meta["mesh"]["colours"] == "vertex" and meta["mesh"]["albedo"] == "file" and meta["mesh"]["watertight"]
    assert meta["framing"]["object_share"] == FRAMINGS["dtu"] and abs(meta["framing"]["measured_share"] - 0.34) < 0.005
    scene = load_scene(root)
    assert scene.fmt == "dtu-colmap" and scene.gt.kind == "dtu"
    # the stl's object samples lie on the 50 mm sphere (up to the icosphere's sag) standing on the table
    stl = np.asarray(trimesh.load(scene.gt.root / "Points" / "stl" / f"stl{scene.gt.scan:03d}_total.ply").vertices)
    top = stl[:, 2].min()
    on_object = stl[stl[:, 2] > top + 1.0]
    centre = np.array([30.0, -20.0, 600.0])  # the DTU layout's object centre in the GT frame (mm)
    sag = 50.0 * (1 - np.linalg.norm(sphere.triangles_center, axis=1).min())  # the mesh's deepest point below the sphere
    assert len(on_object) > 10_000
    assert np.abs(np.linalg.norm(on_object - centre, axis=1) - 50.0).max() < sag + 1e-3
    exact = _eval(root / "gt_mesh.ply", root, tmp_path, "--evaluator", "dtu_chamfer")["dtu_chamfer"]["metrics"]
    # completeness at the 0.2 mm sampling floor; accuracy also scores the mesh's unseen underside, which lies
    # inside ObsMask's 4 mm dilation of the seen band but not in the stl (measured 0.25 mm)
    assert exact["completeness"] < 0.12 and exact["accuracy"] < 0.3
    moved = trimesh.load(root / "gt_mesh.ply", process=False)
    moved.vertices = moved.vertices * 1.02 - centre * 0.02  # a sphere 1 mm larger: not at the floor
    moved.export(tmp_path / "larger.ply")
    assert _eval(tmp_path / "larger.ply", root, tmp_path, "--evaluator", "dtu_chamfer")["dtu_chamfer"]["metrics"]["chamfer"] > 0.5


def test_mesh_scene_is_replanned_from_its_meta(sphere_scene):
    root, _ = sphere_scene
    plan = plan_from_meta(read_meta(root), root)
    scene = load_scene(root, load_images=False)
    assert np.allclose(np.stack([c.center for c in plan.normalised_cameras]), np.stack([c.center for c in scene.cameras]),
                       atol=1e-5)


def test_box_in_both_layouts_has_its_surface_as_ground_truth(tmp_path):
    """A 1 x 0.6 x 0.4 box (OFF): in the DTU (IDR) layout the exact mesh scores completeness at the sampling
    floor; in the TnT layout the GT's object points lie on the box (the ground around it is GT too, so the
    object mesh alone has no F1 of one there)."""
    box = trimesh.Trimesh(*trimesh.remesh.subdivide_to_size(*(lambda b: (b.vertices, b.faces))(
        trimesh.creation.box(extents=(1.0, 0.6, 0.4))), max_edge=0.02))  # dense, as the evaluator's mask culling expects
    box.export(tmp_path / "box.off")
    dtu = make_mesh_scene(tmp_path / "box.off", fmt="dtu", res=RES, out=tmp_path / "box-dtu", rig="cap")
    assert read_meta(dtu)["mesh"]["albedo"] == "procedural" and (dtu / "cameras.npz").is_file()
    metrics = _eval(dtu / "gt_mesh.ply", dtu, tmp_path, "--evaluator", "dtu_chamfer")["dtu_chamfer"]["metrics"]
    assert metrics["completeness"] < 0.12
    import open3d as o3d

    tnt = make_mesh_scene(tmp_path / "box.off", fmt="tnt", framing=None, res=(96, 54), out=tmp_path / "box-tnt")
    assert "framing" not in read_meta(tnt)
    scene = load_scene(tnt, load_images=False)
    gt = np.asarray(trimesh.load(tnt / "box.ply").vertices)
    exact = trimesh.load(tnt / "gt_mesh.ply")  # the dataset (COLMAP) frame
    exact.apply_transform(np.loadtxt(tnt / "box_trans.txt"))  # -> the GT frame
    ground = gt[:, 2].min()
    above = gt[gt[:, 2] > ground + 1e-3]
    assert len(above) > 1000 and scene.gt.tau == pytest.approx(0.005 * 1.5)
    surface = o3d.t.geometry.RaycastingScene()
    surface.add_triangles(o3d.core.Tensor(exact.vertices.astype(np.float32)), o3d.core.Tensor(exact.faces.astype(np.uint32)))
    distance = surface.compute_distance(o3d.core.Tensor(above.astype(np.float32))).numpy()
    assert distance.max() < 1e-5 * 1.5  # float32 on a 1.5 m object


BROKEN = {
    "points.obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\n",
    "nan.obj": "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n",
    "far.obj": "v 1e9 0 0\nv 1e9 0.0001 0\nv 1e9 0 0.0001\nf 1 2 3\n",
    "flat.obj": "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n",
    "garbage.ply": "not a mesh\n",
}


@pytest.mark.parametrize("name", [*BROKEN, "missing.obj", "mesh.xyz"])
def test_broken_mesh_is_a_one_line_error_in_under_five_seconds_before_rendering(tmp_path, name, monkeypatch, capsys):
    path = tmp_path / name
    if name in BROKEN:
        path.write_text(BROKEN[name])
    elif name == "mesh.xyz":
        path.write_text("0 0 0\n")

    def no_render(*args, **kwargs):
        raise AssertionError("the scene renderer was built before the mesh was checked")

    monkeypatch.setattr(Renderer, "__init__", no_render)  # the heavy part: what must not start
    start = time.perf_counter()
    code = main(["scene", "make", "--mesh", str(path), "--out", str(tmp_path / "out")])
    elapsed = time.perf_counter() - start  # the command's own work, not the interpreter's start and imports
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("gsbench: error: ") and "fix:" in lines[0]
    assert name in lines[0] and elapsed < 5.0
    assert not (tmp_path / "out").exists()


def test_repairs_are_made_and_recorded(tmp_path):
    path = tmp_path / "messy.ply"  # a tetrahedron, a duplicate of a face, a face on a NaN vertex, a flat face, a loose vertex
    vertices = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [np.nan, 0, 0], [5, 5, 5], [0.5, 0, 0]]
    faces = [[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2], [2, 1, 0], [0, 1, 4], [0, 1, 6]]
    trimesh.Trimesh(vertices, faces, process=False).export(path)
    obj = read_mesh_object(path, up="z")
    assert len(obj.triangles) == 4
    assert obj.repairs == ["dropped 1 faces with a non-finite vertex coordinate", "dropped 1 faces of zero area",
                           "dropped 1 duplicated faces", "dropped 3 vertices no face uses"]
    assert np.allclose(obj.vertices.min(axis=0), -0.5) and np.allclose(obj.vertices.max(axis=0), 0.5)  # (5,5,5) dropped
    parts = trimesh.util.concatenate([trimesh.creation.box(), trimesh.creation.icosphere(radius=0.1).apply_translation([3, 0, 0])])
    parts.export(tmp_path / "parts.ply")
    largest = read_mesh_object(tmp_path / "parts.ply", up="z", largest_part=True)
    assert len(largest.triangles) == 1280 and largest.repairs[0].startswith("kept the largest of 2 connected parts")
    assert np.allclose(largest.source["extent"], 0.2, atol=1e-6)  # the sphere's, without the box


@pytest.mark.parametrize("up", ["x", "y", "z", "-x", "-y", "-z"])
def test_up_axis_is_turned_onto_z_by_a_rotation(up):
    R = up_rotation(up)
    axis = np.zeros(3)
    axis["xyz".index(up[-1])] = -1.0 if up.startswith("-") else 1.0
    assert np.allclose(R @ axis, [0, 0, 1]) and np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)


def test_texture_and_vertex_colours_come_through(tmp_path):
    """A quad textured with a 2x2 image (red, green / blue, white): each corner's UV gives its texel."""
    texels = np.array([[[255, 0, 0], [0, 255, 0]], [[0, 0, 255], [255, 255, 255]]], dtype=np.uint8)
    Image.fromarray(texels).save(tmp_path / "tex.png")
    (tmp_path / "quad.mtl").write_text("newmtl m\nKd 1 1 1\nmap_Kd tex.png\n")
    (tmp_path / "quad.obj").write_text("mtllib quad.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\n"
                                       "vt 0.25 0.75\nvt 0.75 0.75\nvt 0.75 0.25\nvt 0.25 0.25\n"
                                       "usemtl m\nf 1/1 2/2 3/3\nf 1/1 3/3 4/4\n")
    obj = read_mesh_object(tmp_path / "quad.obj", up="z")
    assert obj.colours == "texture"
    bary = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])  # corners 0, 1, 2 of triangle 0: UV (.25,.75), (.75,.75), (.75,.25)
    rgb = obj.albedo(np.zeros((3, 3)), np.zeros(3, dtype=np.int64), bary)
    assert np.allclose(rgb, [[1, 0, 0], [0, 1, 0], [1, 1, 1]], atol=1e-6)  # v up: UV row 0.75 is the image's top row
    tri = trimesh.creation.box()
    tri.visual.face_colors = [200, 100, 50, 255]
    tri.export(tmp_path / "box.ply")
    faces = read_mesh_object(tmp_path / "box.ply", up="z")
    assert faces.colours in ("face", "vertex")
    assert np.allclose(faces.albedo(np.zeros((1, 3)), np.array([3]), np.array([[0.3, 0.3]])), [[200 / 255, 100 / 255, 50 / 255]])


def test_framing_gives_the_share_asked_for():
    plan = plan_scene("synthetic/dtu-spot", res=RES, framing="dtu")
    assert abs(object_share(Renderer(plan.surface), plan.cameras) - 0.34) < 0.005
    assert plan.distance < 3.5  # closer than the scene's own 3.5 radii
    assert parse_framing("small") == FRAMINGS["small"] and parse_framing("0.2") == 0.2 and parse_framing(None) is None
    for bad in ("1.5", "0", "wide"):
        with pytest.raises(DataError, match="framing"):
            parse_framing(bad)
    with pytest.raises(DataError, match="covers"):
        plan_scene("synthetic/dtu-spot", res=RES, framing=0.95)


@pytest.mark.parametrize("name", ["synthetic/spot", "synthetic/dtu-stool", "synthetic/tnt-yard", "synthetic/dtu-bunny",
                                  "synthetic/dtu-rig-bunny", "synthetic/tnt-rig-spot", "synthetic/tnt-rig-yard"])
def test_listed_share_is_measured(name):
    plan = plan_scene(name, res=(160, 120) if BUILTIN_SCENES[name].format == "dtu" else (192, 108))
    assert abs(object_share(Renderer(plan.surface), plan.cameras) - BUILTIN_SCENES[name].share) < 0.0015


def test_smoothing_takes_the_relief_off_and_keeps_the_shape():
    bunny = "pymeshlab:tests/sample_meshes/bunny.obj"
    from gsbench.data.synthetic.generator import mesh_path

    scanned = read_mesh_object(mesh_path(bunny))
    smooth = read_mesh_object(mesh_path(bunny), smooth=50)
    moved = np.linalg.norm(smooth.vertices - scanned.vertices, axis=1)
    assert 1e-4 < np.sqrt(np.mean(moved**2)) < 3e-3 and smooth.source["taubin_iterations"] == 50
    volume = [trimesh.Trimesh(o.vertices, o.triangles).volume for o in (scanned, smooth)]
    assert abs(volume[1] / volume[0] - 1) < 0.01  # Taubin's low-pass does not shrink it
