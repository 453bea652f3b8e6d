"""Synthetic objects: a triangle mesh in its own "object frame" plus an albedo function.

Object frame: z up, the bounding-box centre at the origin, the largest bounding-box side = 1.
Shapes: ``spot`` (Keenan Crane's Spot, ``gsbench/assets/spot``, public domain; its OBJ is y-up and is
rotated to z-up, head towards +y) and ``plate`` (a 1 x 0.7 x 0.012 box slab, lying in the xy plane).
Albedos: ``texture`` (Spot's UV texture, bilinear), ``procedural`` (a solid 3D texture: a smoothed
checker of random colours times low-frequency sinusoids, so it looks the same from every side and
needs no UVs) and ``uniform`` (one colour).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from gsbench.errors import DataError, import_open3d

ASSETS = Path(__file__).resolve().parent.parent / "assets"
PLATE_SIZE = (1.0, 0.7, 0.012)
CHECKER_PERIOD = 0.125

Albedo = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
"""``albedo(points (N,3), triangle_ids (N,), barycentric (N,2)) -> rgb (N,3)`` in [0, 1]."""


@dataclass
class Surface:
    """A mesh in the object frame and its albedo."""

    vertices: np.ndarray
    triangles: np.ndarray
    albedo: Albedo

    @property
    def radius(self) -> float:
        """Radius of the sphere about the origin that holds the object."""
        return float(np.max(np.linalg.norm(self.vertices, axis=1)))


def _to_object_frame(vertices: np.ndarray) -> np.ndarray:
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
    return _to_object_frame(v), np.asarray(mesh.triangles, dtype=np.int64), uvs


def _texture_albedo(uvs: np.ndarray) -> Albedo:
    from PIL import Image  # noqa: PLC0415
    from scipy.ndimage import map_coordinates  # noqa: PLC0415

    tex = np.asarray(Image.open(ASSETS / "spot" / "spot_texture.png").convert("RGB"), dtype=np.float64) / 255.0
    h, w = tex.shape[:2]

    def albedo(points, tri, bary):
        corners = uvs[tri]
        uv = (1 - bary.sum(axis=1))[:, None] * corners[:, 0] + bary[:, :1] * corners[:, 1] + bary[:, 1:] * corners[:, 2]
        rows, cols = (1.0 - uv[:, 1]) * h - 0.5, uv[:, 0] * w - 0.5  # OBJ v points up; texel centres at +0.5
        return np.stack([map_coordinates(tex[..., c], [rows, cols], order=1, mode="nearest") for c in range(3)], axis=1)

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


def _plate():
    o3d = import_open3d()
    box = o3d.geometry.TriangleMesh.create_box(*PLATE_SIZE)
    return _to_object_frame(np.asarray(box.vertices, dtype=np.float64)), np.asarray(box.triangles, dtype=np.int64)


def make_surface(shape: str, albedo: str, seed: int) -> Surface:
    """Build the named shape with the named albedo (see the module docstring)."""
    uvs = None
    if shape == "spot":
        vertices, triangles, uvs = _read_spot()
    elif shape == "plate":
        vertices, triangles = _plate()
    else:
        raise DataError(f"unknown synthetic shape {shape!r}; expected spot or plate")
    if albedo == "texture":
        if uvs is None:
            raise DataError(f"shape {shape!r} has no UV texture; use albedo procedural or uniform")
        fn = _texture_albedo(uvs)
    elif albedo == "procedural":
        fn = _procedural_albedo(seed)
    elif albedo == "uniform":
        fn = _uniform_albedo()
    else:
        raise DataError(f"unknown albedo {albedo!r}; expected texture, procedural or uniform")
    return Surface(vertices=vertices, triangles=triangles, albedo=fn)
