"""Mesh files in the formats a user brings (PLY, OBJ, STL, OFF, glTF/GLB): read into trimesh, and sized from
their headers before they are read.

`read_mesh_file` is ``trimesh.load(path, process=False)`` (every vertex kept, in the file's order; the
polygons of OBJ, PLY and OFF files split into triangle fans) except for the two layouts trimesh misreads:

- a PLY whose faces are triangle strips (``element tristrips``, as in classic scanned models): trimesh
  returns its vertices alone, a point cloud; pymeshlab unrolls the strips (alternating winding, ``-1``
  restarts) and keeps the vertex colours;
- an OFF with a polygon of five corners or more: trimesh's fan split raises a TypeError under numpy 2 (it
  multiplies strings); open3d reads the file, splitting each polygon into the same fan.

`header_counts` gives (vertices, triangles) from the header where the format has one (PLY, OFF, binary STL),
without reading the rest: a mesh too large for the memory there is can be refused at once.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from gsbench.data.filecheck.ply import ply_element_counts
from gsbench.errors import DataError, import_open3d

STRIPS = "tristrips"  # the PLY element of triangle strips
STL_HEADER, STL_RECORD = 84, 50  # binary STL: 80-byte header + uint32 count, then 50 bytes a triangle
OFF_HEAD = 4096  # bytes read for an OFF file's counts line
READ_FIX = "re-export it as a PLY of triangles"
FACES_PER_VERTEX = 2  # a closed triangle mesh has two faces a vertex (Euler's formula, for many vertices)


def read_mesh_file(path, **load_options) -> trimesh.Trimesh | trimesh.PointCloud | trimesh.Scene:
    """``trimesh.load(path, process=False, **load_options)``, or for the layouts trimesh misreads (module
    docstring) a `trimesh.Trimesh` from pymeshlab or open3d; readers' exceptions pass through."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".ply" and STRIPS in (_ply_counts(path) or {}):
        return _read_with_pymeshlab(path)
    try:
        return trimesh.load(path, process=False, **load_options)
    except TypeError:
        if suffix != ".off":
            raise
        return _read_with_open3d(path)


def _ply_counts(path: Path) -> dict[str, int] | None:
    """The PLY header's element counts, or None when gsbench's header parser refuses it (trimesh then reads
    the file, or says why it cannot)."""
    try:
        return ply_element_counts(path, READ_FIX)
    except DataError:
        return None


def _read_with_pymeshlab(path: Path) -> trimesh.Trimesh:
    import pymeshlab  # noqa: PLC0415  (loads Qt's libraries: imported only when a strip file needs it)

    meshes = pymeshlab.MeshSet()
    meshes.load_new_mesh(str(path))
    mesh = meshes.current_mesh()
    colours = np.rint(mesh.vertex_color_matrix() * 255).astype(np.uint8) if mesh.has_vertex_color() else None
    return trimesh.Trimesh(mesh.vertex_matrix(), mesh.face_matrix(), vertex_colors=colours, process=False)


def _read_with_open3d(path: Path) -> trimesh.Trimesh:
    mesh = import_open3d().io.read_triangle_mesh(str(path))
    colours = np.rint(np.asarray(mesh.vertex_colors) * 255).astype(np.uint8) if mesh.has_vertex_colors() else None
    return trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles), vertex_colors=colours,
                           process=False)


def header_counts(path) -> tuple[int, int] | None:
    """(vertices, faces) as the file's header states them, or None where the format has no header that says
    (OBJ, glTF/GLB, ASCII STL) or the header cannot be parsed. PLY: ``element vertex`` and ``element face`` (a
    polygon counts as one face; a file of triangle strips states how many strips, not triangles, and counts
    `FACES_PER_VERTEX` faces a vertex); OFF: its counts line; binary STL: the triangle count, with three
    vertices each (trimesh merges none)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".ply":
        counts = _ply_counts(path)
        if counts is None:
            return None
        vertices = counts.get("vertex", 0)
        return vertices, FACES_PER_VERTEX * vertices if STRIPS in counts else counts.get("face", 0)
    if suffix == ".off":
        with open(path, "rb") as f:
            lines = f.read(OFF_HEAD).decode("ascii", errors="replace").splitlines()
        words = " ".join(line.split("#")[0] for line in lines).split()
        if len(words) > 2 and words[0].endswith("OFF") and words[1].isdigit() and words[2].isdigit():
            return int(words[1]), int(words[2])
        return None
    if suffix == ".stl":
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(STL_HEADER)
        if len(head) == STL_HEADER:
            triangles = int(np.frombuffer(head[80:84], "<u4")[0])
            if size == STL_HEADER + STL_RECORD * triangles:
                return 3 * triangles, triangles
    return None
