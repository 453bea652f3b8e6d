"""Hostile meshes (issue 65): ``gsbench eval --out`` naming a folder, a mesh too big to evaluate, and meshes in the
older formats a user brings (PLY triangle strips, OBJ quads and n-gons, STL, OFF, glTF/GLB). Each is refused in
one line before any work, or read with its faces."""

from __future__ import annotations

import struct
import time

import numpy as np
import pytest
import trimesh

import gsbench.data.synthetic.make as make
from gsbench.cli import main
from gsbench.data.loader import load_scene
from gsbench.data.synthetic.mesh_file import read_mesh_object
from gsbench.data.synthetic.render import Renderer
from gsbench.errors import EvaluationError
from gsbench.evaluators import api, pointsets
from gsbench.evaluators.dtu_chamfer import check_downsample_memory
from gsbench.evaluators.geometry import read_geometry
from gsbench.mesh.files import header_counts

GIB = 2**30
# a unit cube: corners, and its six faces as quads (counter-clockwise seen from outside)
CUBE = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], dtype=float)
CUBE_QUADS = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
# a hexagonal prism, side 1 and height 1: two hexagons and six quads, area 2 (3 sqrt(3) / 2) + 6
HEXAGON = [[np.cos(a), np.sin(a)] for a in np.arange(6) * np.pi / 3]
PRISM = np.array([[x, y, z] for z in (0.0, 1.0) for x, y in HEXAGON])
PRISM_FACES = [[5, 4, 3, 2, 1, 0], [6, 7, 8, 9, 10, 11], *([k, (k + 1) % 6, (k + 1) % 6 + 6, k + 6] for k in range(6))]
PRISM_AREA = 3 * np.sqrt(3) + 6


def _ply_header(fmt: str, vertices: int, element: str, count: int) -> str:
    return (f"ply\nformat {fmt} 1.0\nelement vertex {vertices}\nproperty float x\nproperty float y\nproperty float z\n"
            f"element {element} {count}\nproperty list int int vertex_indices\nend_header\n")


def _strip_indices() -> list[int]:
    """The cube as six strips of two triangles, one a face (p0, p1, p3, p2: the zig-zag of the quad p0..p3),
    joined by -1 restarts, as classic scanned models store them."""
    indices = []
    for p0, p1, p2, p3 in CUBE_QUADS:
        indices += [p0, p1, p3, p2, -1]
    return indices[:-1]


def _write_formats(folder) -> dict:
    """{file: (triangles, area)} of small meshes in every format a user expects to work."""
    folder.mkdir()
    cube = trimesh.Trimesh(CUBE, [t for q in CUBE_QUADS for t in ([q[0], q[1], q[2]], [q[0], q[2], q[3]])])
    strips = _strip_indices()
    (folder / "strips.ply").write_text(_ply_header("ascii", 8, "tristrips", 1) + "".join(f"{x:g} {y:g} {z:g}\n" for x, y, z in CUBE)
                                       + f"{len(strips)} {' '.join(map(str, strips))}\n")
    with open(folder / "strips_binary.ply", "wb") as f:
        f.write(_ply_header("binary_little_endian", 8, "tristrips", 1).encode())
        f.write(CUBE.astype("<f4").tobytes() + struct.pack("<i", len(strips)) + np.array(strips, "<i4").tobytes())
    (folder / "quads.ply").write_text(_ply_header("ascii", 8, "face", 6) + "".join(f"{x:g} {y:g} {z:g}\n" for x, y, z in CUBE)
                                      + "".join(f"4 {' '.join(map(str, q))}\n" for q in CUBE_QUADS))
    (folder / "quads.obj").write_text("".join(f"v {x:g} {y:g} {z:g}\n" for x, y, z in CUBE)
                                      + "".join(f"f {' '.join(str(i + 1) for i in q)}\n" for q in CUBE_QUADS))
    (folder / "ngons.obj").write_text("".join(f"v {x:g} {y:g} {z:g}\n" for x, y, z in PRISM)
                                      + "".join(f"f {' '.join(str(i + 1) for i in f)}\n" for f in PRISM_FACES))
    (folder / "ngons.off").write_text(f"OFF\n{len(PRISM)} {len(PRISM_FACES)} 0\n" + "".join(f"{x:g} {y:g} {z:g}\n" for x, y, z in PRISM)
                                      + "".join(f"{len(f)} {' '.join(map(str, f))}\n" for f in PRISM_FACES))
    cube.export(folder / "binary.stl")
    (folder / "ascii.stl").write_text(trimesh.exchange.stl.export_stl_ascii(cube))
    cube.export(folder / "cube.glb")
    for name, data in trimesh.Scene(cube).export(file_type="gltf").items():
        (folder / name).write_bytes(data)
    cube_files = ("strips.ply", "strips_binary.ply", "quads.ply", "quads.obj", "binary.stl", "ascii.stl", "cube.glb",
                  "model.gltf")
    return {**{name: (12, 6.0) for name in cube_files}, "ngons.obj": (20, PRISM_AREA), "ngons.off": (20, PRISM_AREA)}


@pytest.fixture(scope="module")
def formats(tmp_path_factory):
    folder = tmp_path_factory.mktemp("formats") / "meshes"
    return folder, _write_formats(folder)


def _area(vertices, faces) -> float:
    tri = np.asarray(vertices)[np.asarray(faces)]
    return float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())


def test_every_format_is_read_with_its_faces_by_eval_and_by_scene_make(formats):
    folder, expected = formats
    for name, (triangles, area) in expected.items():
        geo = read_geometry(folder / name)  # what every evaluator reads
        assert geo.is_mesh and len(geo.faces) == triangles and _area(geo.vertices, geo.faces) == pytest.approx(area), name
        obj = read_mesh_object(folder / name)  # what scene make --mesh reads
        assert len(obj.triangles) == triangles and obj.repairs == [], name
    strips = read_geometry(folder / "strips.ply")
    merged = trimesh.Trimesh(strips.vertices, strips.faces)
    assert merged.is_watertight and merged.is_winding_consistent  # the strips' alternating winding is undone


def test_a_strip_ply_is_evaluated_and_made_into_a_scene(formats, tiny_spot, tmp_path, capsys, monkeypatch):
    """Both commands that refused it as "has no faces (a point cloud?)" now take it."""
    folder, _ = formats
    assert main(["eval", "--mesh", str(folder / "strips.ply"), "--scene", str(tiny_spot), "--evaluator", "mesh_stats"]) == 0
    out, err = capsys.readouterr()
    faces = next(line for line in out.splitlines() if line.split()[:2] == ["mesh_stats@1", "faces"])
    assert faces.split()[2] == "12.0000"
    assert f"gsbench: evaluating {folder / 'strips.ply'} (8 vertices, 16 faces): mesh_stats (1/1, about 1 MiB)" in err

    class Rendering(Exception):
        """Raised where the scene's rendering starts: the mesh was read, checked and framed."""

    def rendering(*args, **kwargs):
        raise Rendering

    monkeypatch.setattr(Renderer, "__init__", rendering)
    with pytest.raises(Rendering):
        main(["scene", "make", "--mesh", str(folder / "strips.ply"), "--res", "32", "24", "--out", str(tmp_path / "s")])


def test_header_counts_need_no_more_than_the_header(formats, tmp_path):
    folder, _ = formats
    assert header_counts(folder / "strips.ply") == (8, 16)  # strips: two faces a vertex
    assert header_counts(folder / "quads.ply") == (8, 6)
    assert header_counts(folder / "ngons.off") == (12, 8)
    assert header_counts(folder / "binary.stl") == (36, 12)
    assert header_counts(folder / "ascii.stl") is None and header_counts(folder / "quads.obj") is None


def _header_only_ply(path, vertices: int, faces: int):
    path.write_text(_ply_header("binary_little_endian", vertices, "face", faces).replace("property list int int",
                                                                                         "property list uchar int"))
    return path


def test_a_mesh_too_big_to_evaluate_is_refused_from_its_header_within_5_s(tiny_spot, tmp_path, capsys, monkeypatch):
    """The issue's 20 M-face PLY printed nothing and reached 20 GB; its header alone now refuses it, on a machine
    with 4 GiB free, naming what each evaluator would need and the face count that fits."""
    big = _header_only_ply(tmp_path / "big.ply", 10_000_000, 20_000_000)
    monkeypatch.setattr(api, "available_memory_bytes", lambda: 4 * GIB)
    start = time.perf_counter()
    code = main(["eval", "--mesh", str(big), "--scene", str(tiny_spot)])
    elapsed = time.perf_counter() - start
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and elapsed < 5.0
    assert lines[0] == (
        f"gsbench: error: {big}: 10,000,000 vertices and 20,000,000 faces need about 7.1 GiB to evaluate (mesh_stats "
        "7.1 GiB, dtu_chamfer 6.7 GiB, silhouette 6.5 GiB, normal_similarity 5.8 GiB; one evaluator at a time, the "
        "scene and its ground truth on top) but 4.0 GiB is available; fix: decimate the mesh to at most 11,000,000 "
        "faces (pymeshlab's meshing_decimation_quadric_edge_collapse(targetfacenum=N), or MeshLab's Quadric Edge "
        "Collapse), leave out mesh_stats (name the other evaluators: --evaluator, or eval.evaluators in a run), or "
        "run it on a larger machine")


def test_a_run_evaluating_its_own_mesh_is_checked_alike(tiny_spot, tmp_path, monkeypatch):
    """`evaluate_mesh_file` (what a run calls on its extracted mesh) refuses before any evaluator reads the file."""
    scene = load_scene(tiny_spot, load_images=False)
    big = _header_only_ply(tmp_path / "mesh.ply", 3_000_000, 6_000_000)
    monkeypatch.setattr(api, "available_memory_bytes", lambda: GIB)
    with pytest.raises(EvaluationError, match=r"mesh.ply: 3,000,000 vertices and 6,000,000 faces need about 2\.1 GiB"):
        api.evaluate_mesh_file(big, scene, ("mesh_stats",))
    monkeypatch.setattr(api, "available_memory_bytes", lambda: 4 * GIB)  # it fits: the reader now says what is wrong
    with pytest.raises(EvaluationError, match="cannot read mesh file"):
        api.evaluate_mesh_file(big, scene, ("mesh_stats",))


def test_a_dense_mesh_is_refused_before_dtu_chamfer_downsamples_it():
    """dtu_chamfer's 0.2 mm downsampling holds every pair of points closer than 0.2 mm: their number, estimated from
    a sample, is checked against the memory before they are found."""
    n, degree, radius = 200_000, 30, 0.2
    side = np.sqrt(n * np.pi * radius**2 / degree)  # a plane of points with `degree` neighbours within the radius
    points = np.random.default_rng(0).random((n, 3)) * [side, side, 0.0]
    pairs = len(pointsets.radius_pairs(points, radius)[0])
    assert pointsets.radius_pair_estimate(points, radius) == pytest.approx(pairs, rel=0.05)
    assert pointsets.greedy_downsample_memory(n, pairs) == pytest.approx(112 * n + 10 * pairs + 40 * pairs / n * min(n, 500_000))
    with pytest.raises(EvaluationError, match=r"downsampling the 200,000 points of dense.ply at 0.2 mm holds every pair "
                                              r"closer than that, about 2,\d\d\d,\d\d\d: 1\d\d MiB in all, but 100 MiB is "
                                              r"available; fix: decimate the mesh"):
        check_downsample_memory(points, radius, "dense.ply", available=100 * 2**20)
    check_downsample_memory(points, radius, "dense.ply", available=GIB)


def test_eval_out_naming_a_folder_is_refused_before_any_work(tmp_path, capsys, monkeypatch):
    mesh = tmp_path / "mesh.ply"
    trimesh.creation.icosphere().export(mesh)

    def no_work(*args, **kwargs):
        raise AssertionError("the scene was made or read before --out was checked")

    monkeypatch.setattr(make, "ensure_scene", no_work)
    assert main(["eval", "--mesh", str(mesh), "--scene", "synthetic/spot", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err == (f"gsbench: error: --out {tmp_path}: is a folder, and the results are one JSON file; fix: name a "
                   f"file, e.g. --out {tmp_path / 'eval.json'}\n")
