"""Synthetic objects: a triangle mesh in its own "object frame" plus an albedo function.

Object frame: z up, the bounding-box centre at the origin, the largest bounding-box side = 1.
Shapes: ``spot`` (Keenan Crane's Spot, ``gsbench/assets/spot``, public domain; its OBJ is y-up and is
rotated to z-up, head towards +y), ``plate`` (a 1 x 0.7 x 0.012 box slab, lying in the xy plane) and
the procedural objects of ``objects.py`` (``stool``, ``bowl``, ``vase``, ``pebbles``, ``blocks``).
Albedos: ``texture`` (Spot's UV texture, bilinear), ``procedural`` (a solid 3D texture: a smoothed
checker of random colours times low-frequency sinusoids, so it looks the same from every side and
needs no UVs), ``uniform`` (one colour), and the solid textures of ``textures.py`` named ``wood``,
``glaze``, ``fine``, ``stone`` (mottled grey-beige plaster noise at 0.06 object units, for a statue),
``facade`` (walls with windows, gravel roofs) and ``painted`` (one colour per face direction, from the
triangle normals, times a fine grain). Objects read from mesh files (``mesh_file.py``) take their own
colours or one of these named albedos (`named_albedo`).

A `Surface` may hold several parts (an object standing in its environment, ``environment.py``):
``parts`` then gives each triangle's part index, part 0 being the object, and ``unlit`` (optional,
bool per triangle) marks self-luminous triangles (a sky) that the renderer shows unshaded.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.ndimage import map_coordinates

from gsbench.data.synthetic import textures
from gsbench.data.synthetic.objects import BUILDERS
from gsbench.data.synthetic.primitives import Albedo, Surface, triangle_normals
from gsbench.data.synthetic.textures import Noise, facade, wood
from gsbench.errors import DataError, import_open3d

ASSETS = Path(__file__).resolve().parents[2] / "assets"
PLATE_SIZE = (1.0, 0.7, 0.012)
CHECKER_PERIOD = 0.125


def to_object_frame(vertices: np.ndarray) -> np.ndarray:
    """Centre the bounding box at the origin and scale its largest side to 1."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    return (vertices - (lo + hi) / 2) / float(np.max(hi - lo))


def _read_spot():
    o3d = import_open3d()
    path = ASSETS / "spot" / "spot_triangulated.obj"
    mesh = o3d.io.read_triangle_mesh(str(path), enable_post_processing=False)
    if len(mesh.triangles) == 0 or len(mesh.triangle_uvs) != 3 * len(mesh.triangles):
        raise DataError(f"{path}: Spot mesh or its UVs could not be read; fix: reinstall gsbench (the asset ships with it)")
    v = np.asarray(mesh.vertices, dtype=np.float64)
    v = np.stack([v[:, 0], -v[:, 2], v[:, 1]], axis=1)  # y-up -> z-up (rotation about x by +90 degrees)
    uvs = np.asarray(mesh.triangle_uvs, dtype=np.float64).reshape(-1, 3, 2)
    return to_object_frame(v), np.asarray(mesh.triangles, dtype=np.int64), uvs


def texture_albedo(uvs: np.ndarray, image: np.ndarray) -> Albedo:
    """A UV texture: per-corner UVs (T,3,2) interpolated with the hit's barycentric coordinates, the
    image (H,W,3, [0, 1]) sampled bilinearly (v up as in OBJ, texel centres at +0.5, edges clamped)."""
    h, w = image.shape[:2]

    def albedo(points, tri, bary):
        corners = uvs[tri]
        uv = (1 - bary.sum(axis=1))[:, None] * corners[:, 0] + bary[:, :1] * corners[:, 1] + bary[:, 1:] * corners[:, 2]
        rows, cols = (1.0 - uv[:, 1]) * h - 0.5, uv[:, 0] * w - 0.5
        return np.stack([map_coordinates(image[..., c], [rows, cols], order=1, mode="nearest") for c in range(3)], axis=1)

    return albedo


def _procedural_albedo(seed: int) -> Albedo:
    rng = np.random.default_rng(seed)
    c1, c2 = rng.uniform(0.15, 0.9, size=(2, 3))
    directions = rng.normal(size=(4, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    freqs, phases = rng.uniform(3.0, 9.0, size=4), rng.uniform(0, 2 * np.pi, size=4)
    offset = rng.uniform(0.2, 0.8, size=3) * CHECKER_PERIOD  # keeps the checker alive on the planes x, y, z = 0

    def albedo(points, tri, bary):
        s = np.prod(np.sin(np.pi * (points + offset) / CHECKER_PERIOD), axis=1)
        mix = 0.5 + 0.5 * np.tanh(8.0 * s)
        wave = 1.0 + 0.12 * np.sin(2 * np.pi * (points @ directions.T) * freqs + phases).sum(axis=1)
        return np.clip((c1 + (c2 - c1) * mix[:, None]) * wave[:, None], 0.0, 1.0)

    return albedo


def _uniform_albedo(color=(0.72, 0.62, 0.5)) -> Albedo:
    c = np.asarray(color, dtype=np.float64)
    return lambda points, tri, bary: np.broadcast_to(c, (len(points), 3)).copy()


@lru_cache(maxsize=8)
def _built_cached(shape: str):
    vertices, triangles = BUILDERS[shape]()
    return to_object_frame(vertices), triangles


def _built(shape: str):
    """A procedural object (objects.py) in the object frame; memoised (marching cubes takes seconds)."""
    vertices, triangles = _built_cached(shape)
    return vertices.copy(), triangles.copy()


def _plate():
    o3d = import_open3d()
    box = o3d.geometry.TriangleMesh.create_box(*PLATE_SIZE)
    return to_object_frame(np.asarray(box.vertices, dtype=np.float64)), np.asarray(box.triangles, dtype=np.int64)


def _painted_albedo(vertices: np.ndarray, triangles: np.ndarray, seed: int) -> Albedo:
    palette = np.array([(0.82, 0.22, 0.16), (0.95, 0.78, 0.22), (0.22, 0.45, 0.78), (0.3, 0.62, 0.32),
                        (0.85, 0.85, 0.8), (0.55, 0.3, 0.6)])
    e1, e2 = vertices[triangles[:, 1]] - vertices[triangles[:, 0]], vertices[triangles[:, 2]] - vertices[triangles[:, 0]]
    n = np.cross(e1, e2)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    sector = np.floor(np.mod(np.arctan2(n[:, 1], n[:, 0]) / (2 * np.pi) * 5 + 0.5, 5)).astype(np.int64)
    colour = np.where(n[:, 2] > 0.9, 4, np.where(n[:, 2] < -0.9, 5, sector % 4))
    noise = Noise(seed)

    def albedo(points, tri, bary):
        grain = 0.72 + 0.56 * noise.fbm(points, 0.025, 4)
        return np.clip(palette[colour[tri]] * grain[:, None], 0.0, 1.0)

    return albedo


TEXTURE_ALBEDOS = ("wood", "glaze", "fine", "stone")
NAMED_ALBEDOS = ("procedural", "uniform", "painted", "facade") + TEXTURE_ALBEDOS


def named_albedo(albedo: str, vertices: np.ndarray, triangles: np.ndarray, seed: int) -> Albedo:
    """The albedo called ``albedo`` (module docstring) for a mesh in the object frame."""
    if albedo == "procedural":
        return _procedural_albedo(seed)
    if albedo == "uniform":
        return _uniform_albedo()
    if albedo == "painted":
        return _painted_albedo(vertices, triangles, seed)
    if albedo == "facade":
        return facade(seed, triangle_normals(vertices, triangles), window=(0.02, 0.03), floor_height=0.06)
    if albedo == "wood":
        return wood(seed, light=(0.66, 0.38, 0.24), dark=(0.3, 0.14, 0.07), plank=0.3, ring=0.02)
    if albedo == "stone":
        return textures.plaster(seed, color=(0.72, 0.66, 0.58), cell=0.06, contrast=0.8)
    if albedo in TEXTURE_ALBEDOS:
        return getattr(textures, albedo)(seed)
    raise DataError(f"unknown albedo {albedo!r}; expected texture or one of {', '.join(NAMED_ALBEDOS)}")


def make_surface(shape: str, albedo: str, seed: int) -> Surface:
    """Build the named shape with the named albedo (see the module docstring)."""
    uvs = None
    if shape == "spot":
        vertices, triangles, uvs = _read_spot()
    elif shape == "plate":
        vertices, triangles = _plate()
    elif shape in BUILDERS:
        vertices, triangles = _built(shape)
    else:
        raise DataError(f"unknown synthetic shape {shape!r}; expected spot, plate or one of {sorted(BUILDERS)}")
    if albedo == "texture":
        if uvs is None:
            raise DataError(f"shape {shape!r} has no UV texture; use albedo procedural or uniform")
        image = np.asarray(Image.open(ASSETS / "spot" / "spot_texture.png").convert("RGB"), dtype=np.float64) / 255.0
        fn = texture_albedo(uvs, image)
    else:
        fn = named_albedo(albedo, vertices, triangles, seed)
    return Surface(vertices=vertices, triangles=triangles, albedo=fn)
