"""A triangle mesh file as a synthetic object: read, checked, repaired, turned z-up and coloured.

`read_mesh_object(path, up, yaw, largest_part)` reads OBJ, PLY (triangle strips too), GLB/glTF, OFF or STL
(`gsbench.mesh.files.read_mesh_file`: trimesh with no processing, so UV seams and vertex colours stay as the
file has them) and returns the object in the object frame of ``shapes.py`` (z up, bounding-box centre at the
origin, largest side 1) with the colours the file carries, if any:

- ``texture``: per-corner UVs and the material's image, sampled bilinearly at the barycentric UV;
- ``vertex`` / ``face``: the file's colours, interpolated barycentrically (vertex) or per face.

Checks, before anything heavy, each a one-line `DataError` naming the file and the fix: the file
exists and has a supported suffix, it parses, it has faces, some face is finite and has an area, and
the object is not lost to float precision (its size below 1e-6 of its distance from the file's
origin: "absurd units"). Repairs, each written into ``repairs`` (and so into the scene's
``gsbench_scene.json``): faces with a non-finite vertex, faces of zero area and duplicated faces are
dropped; unreferenced vertices are dropped (they would widen the bounding box); with ``largest_part``
only the largest connected part (by face count) is kept, as for a range scan with loose fragments.

Orientation: ``up`` names the file's up axis (``y`` for OBJ/glTF convention, ``z`` for most scans
exported z-up; a leading ``-`` flips it); it is turned onto +z by a proper rotation, and then the
object is turned by ``yaw`` degrees about z (the DTU-like camera cap looks from +y).

An open surface (a range map, a single-sided sheet) needs no repair: rendering, masks and the DTU
ground truth (the surface samples seen by at least two views) are all made from ray hits. What an
open surface has no defined inside for is the table-contact test of `groundtruth.sample_world_gt`;
``watertight`` is recorded so a reader knows.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from gsbench.data.synthetic.primitives import Albedo
from gsbench.data.synthetic.shapes import texture_albedo, to_object_frame
from gsbench.errors import DataError
from gsbench.mesh.files import read_mesh_file

MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".off", ".stl")
UP_AXES = ("x", "y", "z", "-x", "-y", "-z")
PRECISION_LIMIT = 1e-6  # object size / distance from the file's origin below this: float precision is gone
TAUBIN_LAMBDA, TAUBIN_MU = 0.5, 0.53  # trimesh's nu is |mu|
AREA_FLOOR = 1e-14  # x the squared object size: faces smaller than this have no area


@dataclass
class MeshObject:
    """A mesh file's object: vertices (V,3) in the object frame, triangles (T,3), the file's colours
    (``albedo``, None when it has none) and what was read and repaired."""

    vertices: np.ndarray
    triangles: np.ndarray
    albedo: Albedo | None
    colours: str
    repairs: list[str] = field(default_factory=list)
    source: dict = field(default_factory=dict)


def file_digest(path: Path) -> str:
    """SHA-256 of a file's bytes (the scene's meta records it, so a changed file is noticed)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def up_rotation(up: str) -> np.ndarray:
    """The proper rotation taking the axis ``up`` (``x``, ``-y``, ...) onto +z."""
    if up not in UP_AXES:
        raise DataError(f"unknown up axis {up!r}; fix: one of {', '.join(UP_AXES)}")
    sign = -1.0 if up.startswith("-") else 1.0
    axis = "xyz".index(up[-1])
    if axis == 2:
        return np.diag([1.0, sign, sign])  # z: identity; -z: half a turn about x
    a = np.zeros(3)
    a[axis] = sign
    k = np.cross(a, [0.0, 0.0, 1.0])  # rotation by 90 degrees about a x z takes a to z
    k /= np.linalg.norm(k)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + K + K @ K


def _load(path: Path) -> trimesh.Trimesh:
    if not path.is_file():
        raise DataError(f"{path}: mesh file not found; fix: give an existing {'/'.join(s[1:] for s in MESH_SUFFIXES)} file")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise DataError(f"{path}: unsupported mesh suffix {path.suffix!r}; fix: convert it to one of {', '.join(MESH_SUFFIXES)}")
    try:
        mesh = read_mesh_file(path, force="mesh")
    except Exception as exc:  # trimesh raises whatever its parsers raise
        raise DataError(f"{path}: could not be read as a mesh ({type(exc).__name__}: {exc}); fix: check the file "
                        "opens in a mesh viewer, or re-export it") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(getattr(mesh, "faces", ())) == 0:
        raise DataError(f"{path}: has no faces (a point cloud or an empty scene?); fix: give a triangle mesh")
    return mesh


def _corner_colours(mesh: trimesh.Trimesh, path: Path) -> tuple[str, Albedo | None, np.ndarray | None]:
    """(kind, albedo maker input) of the file's colours: per-corner UVs + image, or per-corner RGB."""
    visual = mesh.visual
    faces = np.asarray(mesh.faces)
    if visual.kind == "texture" and getattr(visual, "uv", None) is not None and len(visual.uv) == len(mesh.vertices):
        material = visual.material
        image = getattr(material, "image", None) or getattr(material, "baseColorTexture", None)
        if image is not None:
            return "texture", np.asarray(image.convert("RGB"), dtype=np.float64) / 255.0, np.asarray(visual.uv)[faces]
        colour = getattr(material, "diffuse", None)
        if colour is None:
            colour = getattr(material, "baseColorFactor", None)
        if colour is not None:
            rgb = np.asarray(colour, dtype=np.float64)[:3]
            rgb = rgb / 255.0 if rgb.max() > 1.0 else rgb
            return "material", None, np.broadcast_to(rgb, (len(faces), 3, 3)).copy()
    if visual.kind == "vertex":
        return "vertex", None, np.asarray(visual.vertex_colors, dtype=np.float64)[faces, :3] / 255.0
    if visual.kind == "face":
        rgb = np.asarray(visual.face_colors, dtype=np.float64)[:, :3] / 255.0
        return "face", None, np.repeat(rgb[:, None], 3, axis=1)
    return "none", None, None


def corner_colour_albedo(corners: np.ndarray) -> Albedo:
    """Per-corner RGB (T,3,3) interpolated with the hit's barycentric coordinates."""

    def albedo(points, tri, bary):
        c = corners[tri]
        return (1 - bary.sum(axis=1))[:, None] * c[:, 0] + bary[:, :1] * c[:, 1] + bary[:, 1:] * c[:, 2]

    return albedo


def read_mesh_object(path, up: str = "y", yaw: float = 0.0, largest_part: bool = False, smooth: int = 0) -> MeshObject:
    """Read, check and repair ``path`` and put it in the object frame (module docstring); ``smooth`` > 0
    runs that many iterations of Taubin smoothing (λ = 0.5, μ = -0.53: low-pass without shrinking,
    Taubin 1995) to take the fine relief off a scan while keeping its shape."""
    path = Path(path)
    rotation = up_rotation(up)
    mesh = _load(path)
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    colours, image, corners = _corner_colours(mesh, path)
    repairs = []
    keep = np.all(np.isfinite(vertices[faces]).reshape(len(faces), -1), axis=1)
    if not keep.all():
        repairs.append(f"dropped {int((~keep).sum())} faces with a non-finite vertex coordinate")
    if not keep.any():
        raise DataError(f"{path}: every face has a non-finite (NaN or infinite) vertex; fix: re-export the mesh")
    used = vertices[np.unique(faces[keep])]
    lo, hi = used.min(axis=0), used.max(axis=0)
    size = float(np.max(hi - lo))
    reach = float(np.max(np.abs(used)))
    if size <= PRECISION_LIMIT * max(reach, 1e-300):
        raise DataError(f"{path}: the object is {size:.3g} units across but lies {reach:.3g} units from the file's origin "
                        "(absurd units: float precision cannot hold its shape); fix: centre and rescale the mesh before export")
    corner_pos = np.where(keep[:, None, None], vertices[np.where(keep[:, None], faces, 0)], 0.0)
    area = 0.5 * np.linalg.norm(np.cross(corner_pos[:, 1] - corner_pos[:, 0], corner_pos[:, 2] - corner_pos[:, 0]), axis=1)
    flat = keep & ~(area > AREA_FLOOR * size**2)
    if flat.any():
        repairs.append(f"dropped {int(flat.sum())} faces of zero area")
    keep &= ~flat
    if not keep.any():
        raise DataError(f"{path}: no face has an area (all degenerate); fix: give a mesh with real triangles")
    _, first = np.unique(np.sort(faces, axis=1), axis=0, return_index=True)
    duplicate = keep & ~np.isin(np.arange(len(faces)), first)
    if duplicate.any():
        repairs.append(f"dropped {int(duplicate.sum())} duplicated faces")
    keep &= ~duplicate
    if largest_part:
        ids = np.flatnonzero(keep)
        labels = trimesh.graph.connected_component_labels(trimesh.graph.face_adjacency(faces[ids]), node_count=len(ids))
        counts = np.bincount(labels)
        if len(counts) > 1:
            repairs.append(f"kept the largest of {len(counts)} connected parts ({counts.max()} faces; dropped "
                           f"{len(ids) - counts.max()} faces of the others)")
            keep[ids[labels != counts.argmax()]] = False
    faces, corners = faces[keep], None if corners is None else corners[keep]
    referenced, inverse = np.unique(faces, return_inverse=True)
    if len(referenced) < len(vertices):
        repairs.append(f"dropped {len(vertices) - len(referenced)} vertices no face uses")
    triangles = inverse.reshape(-1, 3).astype(np.int64)
    oriented = vertices[referenced] @ rotation.T
    c, s = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
    oriented = oriented @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T
    oriented_mesh = trimesh.Trimesh(oriented, triangles, process=False)
    if smooth > 0:
        trimesh.smoothing.filter_taubin(oriented_mesh, lamb=TAUBIN_LAMBDA, nu=TAUBIN_MU, iterations=int(smooth))
        oriented = np.asarray(oriented_mesh.vertices)
    watertight = bool(oriented_mesh.is_watertight)
    albedo = None
    if colours == "texture":
        albedo = texture_albedo(corners, image)
    elif corners is not None:
        albedo = corner_colour_albedo(corners)
    source = {"path": str(path.resolve()), "sha256": file_digest(path), "faces_read": int(len(mesh.faces)),
              "vertices_read": int(len(mesh.vertices)), "faces": int(len(triangles)), "extent": [float(v) for v in np.ptp(vertices[referenced], axis=0)],
              "colours": colours, "up": up, "yaw": float(yaw), "watertight": watertight}
    if smooth > 0:
        source["taubin_iterations"] = int(smooth)
    return MeshObject(vertices=to_object_frame(oriented), triangles=triangles, albedo=albedo, colours=colours,
                      repairs=repairs, source=source)
