"""The building blocks of the synthetic scenes: triangle meshes as (vertices (V,3), triangles (T,3)) pairs
(quads, boxes, cylinders, domes, discs, their normals and their union) and the `Surface` a scene is made of
(a mesh in the object frame with its albedo function)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import trimesh

Albedo = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
"""``albedo(points (N,3), triangle_ids (N,), barycentric (N,2)) -> rgb (N,3)`` in [0, 1]."""


@dataclass
class Surface:
    """A mesh in the object frame and its albedo."""

    vertices: np.ndarray
    triangles: np.ndarray
    albedo: Albedo
    parts: np.ndarray | None = None
    unlit: np.ndarray | None = None

    @property
    def radius(self) -> float:
        """Radius of the sphere about the origin that holds the object."""
        return float(np.max(np.linalg.norm(self.vertices, axis=1)))


def regular_polygon(radius: float, count: int, centre=(0.0, 0.0)) -> np.ndarray:
    a = 2 * np.pi * np.arange(count) / count
    return np.asarray(centre, float) + radius * np.stack([np.cos(a), np.sin(a)], axis=1)


def quad(a, b, c, d) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles a b c, a c d (normal along (b - a) x (c - a))."""
    return np.array([a, b, c, d], dtype=np.float64), np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)


def box(lo, hi, inward: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box [lo, hi]: 8 vertices, 12 triangles, normals outward (or inward)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    m = trimesh.creation.box(extents=hi - lo)
    v = np.asarray(m.vertices) + (lo + hi) / 2
    f = np.asarray(m.faces, dtype=np.int64)
    return v, (f[:, ::-1] if inward else f)


def cylinder(centre_xy, radius, z0, z1, sections: int = 48) -> tuple[np.ndarray, np.ndarray]:
    m = trimesh.creation.cylinder(radius=radius, height=z1 - z0, sections=sections)
    v = np.asarray(m.vertices) + np.array([centre_xy[0], centre_xy[1], (z0 + z1) / 2])
    return v, np.asarray(m.faces, dtype=np.int64)


def dome(radius: float, z0: float, rings: int = 24, sectors: int = 96) -> tuple[np.ndarray, np.ndarray]:
    """Upper hemisphere of ``radius`` about (0, 0, z0), normals inward, its rim at z0."""
    el = np.linspace(0.0, np.pi / 2, rings + 1)[:-1]
    az = 2 * np.pi * np.arange(sectors) / sectors
    e, a = np.meshgrid(el, az, indexing="ij")
    v = np.stack([radius * np.cos(e) * np.cos(a), radius * np.cos(e) * np.sin(a), z0 + radius * np.sin(e)], -1).reshape(-1, 3)
    v = np.vstack([v, [0.0, 0.0, z0 + radius]])
    i, j = np.arange(sectors), (np.arange(sectors) + 1) % sectors
    faces = []
    for k in range(rings - 1):
        a0, a1 = k * sectors, (k + 1) * sectors
        faces += [np.stack([a0 + i, a1 + j, a0 + j], 1), np.stack([a0 + i, a1 + i, a1 + j], 1)]
    top = len(v) - 1
    last = (rings - 1) * sectors
    faces.append(np.stack([last + i, np.full(sectors, top), last + j], 1))
    return v, np.concatenate(faces).astype(np.int64)


def disc(radius: float, z: float, sectors: int = 96) -> tuple[np.ndarray, np.ndarray]:
    """A flat disc (fan about the centre) facing +z."""
    v = np.vstack([[0.0, 0.0, z], np.column_stack([regular_polygon(radius, sectors), np.full(sectors, z)])])
    i = np.arange(sectors)
    return v, np.stack([np.zeros(sectors, dtype=np.int64), 1 + i, 1 + (i + 1) % sectors], 1)


def triangle_normals(v: np.ndarray, t: np.ndarray) -> np.ndarray:
    n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def merge(meshes) -> tuple[np.ndarray, np.ndarray]:
    """Concatenate (vertices, triangles) pairs into one mesh."""
    vs, ts, n = [], [], 0
    for v, t in meshes:
        vs.append(v)
        ts.append(t + n)
        n += len(v)
    return np.concatenate(vs), np.concatenate(ts)
