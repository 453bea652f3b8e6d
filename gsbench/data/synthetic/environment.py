"""Surroundings of a synthetic object: the parts rendered with it and the region its GT covers.

A `World` is the object (part 0) plus environment parts, all in the object frame (z up, the object's
lowest point at ``ground_z``), ray-cast together as one `Surface` whose ``parts`` array gives each
triangle's part index (the mask of a view = pixels whose centre ray hits part 0). Part roles:
``object`` (part 0), ``ground`` (the table top / ground plane: in the GT inside ``gt_polygon``),
``prop`` (other solids: never in the GT, placed outside the GT region) and ``backdrop`` (room walls,
domes: never in the GT). Sky domes are unlit (shown with their albedo, no shading). Lengths below
are in units of the object's radius ``r`` (`Surface.radius`) unless they say "object units" (the
object's largest bounding-box side = 1).

Environments (`make_environment`):

- ``room`` (DTU-like): a wooden table (slab x, y in [-4r, 4r], 0.4r thick, its top exactly at the
  object's lowest point, four legs) in a room seen from inside: x, y in [-9r, 9r], floor 5r below
  the table top, ceiling 9r above it; tiled floor, brick and wallpaper walls, plaster ceiling. The
  cameras (``cap`` rig at 3.5r) are all inside the room, above the table. GT region: the table top
  within a disk of radius 0.8 object units about the object's axis (DTU's scanner sees the table
  around the object), as a regular 256-gon.
- ``ground`` (TnT-like, ``tnt-spot``): a cobbled ground square of half side 40 object units, six
  props (crates and barrels) at 1.1-1.4 object units from the object, and a square courtyard of
  brick and plaster facades with windows (half side 10 object units, 8 high) closing every view. GT
  region: the object's xy convex hull grown by 0.3 object units.
- ``yard`` (TnT-like, ``tnt-yard``): the object is a cluster of building blocks; around it a ring of
  taller buildings (2-3 object units out) and a sky dome of radius 40 object units. GT region: the
  cluster's hull grown by 0.06 object units.
- ``sky`` (TnT-like, ``tnt-sky``): the object on a meadow disc of radius 100 object units under a
  sky dome of the same radius (mountains and clouds; 100 x the object size, out of reach of any
  reconstruction and outside the crop). GT region: the object's hull grown by 0.3 object units.

The GT z range is [ground_z - 0.02, top + 0.02] object units (top = the highest object point).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import ConvexHull

from gsbench.data.synthetic import textures
from gsbench.data.synthetic.primitives import (
    Albedo,
    Surface,
    box,
    cylinder,
    disc,
    dome,
    merge,
    quad,
    regular_polygon,
    triangle_normals,
)
from gsbench.errors import DataError

DTU_GT_DISK = 0.8  # object units: radius of the table region in the DTU GT
CROP_Z_MARGIN = 0.02  # object units
ROLES = ("object", "ground", "prop", "backdrop")


@dataclass
class Part:
    """One piece of a world: a mesh in the object frame, its albedo and its role (module docstring)."""

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    albedo: Albedo
    role: str
    lit: bool = True


@dataclass
class World:
    """The object (part 0) in its environment; ``gt_polygon`` (convex, counter-clockwise, xy) and
    ``gt_z`` = (z_min, z_max) bound the region whose surfaces form the GT (object frame)."""

    parts: list[Part]
    ground_z: float
    gt_polygon: np.ndarray
    gt_z: tuple[float, float]
    kind: str = ""

    @cached_property
    def surface(self) -> Surface:
        """All parts as one `Surface` (part index per triangle; albedo dispatched by part)."""
        offsets = np.cumsum([0] + [len(p.triangles) for p in self.parts])
        vstarts = np.cumsum([0] + [len(p.vertices) for p in self.parts])
        vertices = np.concatenate([p.vertices for p in self.parts])
        triangles = np.concatenate([p.triangles + v0 for p, v0 in zip(self.parts, vstarts)])
        part_of = np.concatenate([np.full(len(p.triangles), k, dtype=np.int32) for k, p in enumerate(self.parts)])
        parts = self.parts

        def albedo(points, tri, bary):
            out = np.zeros((len(points), 3))
            which = part_of[tri]
            for k in np.unique(which):
                sel = which == k
                out[sel] = parts[k].albedo(points[sel], tri[sel] - offsets[k], bary[sel])
            return out

        unlit = None
        if not all(p.lit for p in parts):
            unlit = np.array([not p.lit for p in parts])[part_of]
        return Surface(vertices=vertices, triangles=triangles, albedo=albedo, parts=part_of, unlit=unlit)

    @property
    def object(self) -> Part:
        return self.parts[0]

    def inside_gt_region(self, points: np.ndarray) -> np.ndarray:
        """Points (N,3) inside the GT prism: the polygon in xy and ``gt_z`` in z."""
        return inside_polygon(points[:, :2], self.gt_polygon) & (points[:, 2] >= self.gt_z[0]) & (points[:, 2] <= self.gt_z[1])


def inside_polygon(xy: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Points inside a convex counter-clockwise polygon (on the edge counts as inside): each point is
    tested against the one edge of the angular sector (about the vertex mean) it falls in."""
    centre = polygon.mean(axis=0)
    start = np.mod(np.arctan2(*(polygon - centre)[:, ::-1].T), 2 * np.pi)
    order = np.argsort(start)
    a = polygon[order]
    b = np.roll(a, -1, axis=0)
    angle = np.mod(np.arctan2(xy[:, 1] - centre[1], xy[:, 0] - centre[0]), 2 * np.pi)
    k = (np.searchsorted(start[order], angle, side="right") - 1) % len(a)
    p, q = a[k], b[k]
    return (q[:, 0] - p[:, 0]) * (xy[:, 1] - p[:, 1]) - (q[:, 1] - p[:, 1]) * (xy[:, 0] - p[:, 0]) >= -1e-12


def grown_hull(xy: np.ndarray, margin: float, count: int = 64) -> np.ndarray:
    """The convex hull of ``xy`` grown by ``margin`` (Minkowski sum with a ``count``-gon), counter-clockwise."""
    a = 2 * np.pi * np.arange(count) / count
    disc = margin / np.cos(np.pi / count) * np.stack([np.cos(a), np.sin(a)], axis=1)
    hull = xy[ConvexHull(xy).vertices]
    pts = (hull[:, None, :] + disc[None]).reshape(-1, 2)
    return pts[ConvexHull(pts).vertices]


def _object_part(surface: Surface) -> Part:
    return Part("object", surface.vertices, surface.triangles, surface.albedo, "object")


def _room(surface: Surface, seed: int) -> World:
    r, zt = surface.radius, float(surface.vertices[:, 2].min())
    parts = [_object_part(surface)]
    top = box((-4 * r, -4 * r, zt - 0.4 * r), (4 * r, 4 * r, zt))
    floor_z, ceil_z, w = zt - 5 * r, zt + 9 * r, 9 * r
    legs = merge(box((sx * 3.5 * r - 0.2 * r, sy * 3.5 * r - 0.2 * r, floor_z), (sx * 3.5 * r + 0.2 * r, sy * 3.5 * r + 0.2 * r, zt - 0.4 * r))
                 for sx in (-1, 1) for sy in (-1, 1))
    parts.append(Part("table", *top, textures.wood(seed + 11, plank=1.0, ring=0.06), "ground"))
    parts.append(Part("table legs", *legs, textures.wood(seed + 12, plank=0.4, ring=0.05, axes=(2, 0)), "prop"))
    c = [(-w, -w), (w, -w), (w, w), (-w, w)]
    parts.append(Part("floor", *quad(*[(x, y, floor_z) for x, y in c]), textures.tiles(seed + 13, tile=1.5), "backdrop"))
    parts.append(Part("ceiling", *quad(*[(x, y, ceil_z) for x, y in c[::-1]]), textures.plaster(seed + 14, cell=1.0), "backdrop"))
    walls = [
        ("wall -y", [(-w, -w, floor_z), (w, -w, floor_z), (w, -w, ceil_z), (-w, -w, ceil_z)], textures.bricks(seed + 15, (0.6, 0.2), axes=(0, 2))),
        ("wall +x", [(w, -w, floor_z), (w, w, floor_z), (w, w, ceil_z), (w, -w, ceil_z)],
         textures.plaster(seed + 16, (0.55, 0.68, 0.62), cell=0.5, contrast=0.8)),
        ("wall +y", [(w, w, floor_z), (-w, w, floor_z), (-w, w, ceil_z), (w, w, ceil_z)],
         textures.bricks(seed + 17, (0.5, 0.18), color=(0.55, 0.45, 0.35), axes=(0, 2))),
        ("wall -x", [(-w, w, floor_z), (-w, -w, floor_z), (-w, -w, ceil_z), (-w, w, ceil_z)],
         textures.tiles(seed + 18, (0.8, 0.75, 0.6), (0.6, 0.3, 0.25), tile=0.7, axes=(1, 2))),
    ]
    parts += [Part(name, *quad(*corners), albedo, "backdrop") for name, corners, albedo in walls]
    top_z = float(surface.vertices[:, 2].max())
    return World(parts, zt, regular_polygon(DTU_GT_DISK, 256), (zt - CROP_Z_MARGIN, top_z + CROP_Z_MARGIN), "room")


def _props(seed: int, zg: float, radii=(1.4, 1.9), count: int = 6) -> list[Part]:
    rng = np.random.default_rng(seed + 21)
    azimuths = 2 * np.pi * (np.arange(count) + rng.uniform(0.1, 0.9, count)) / count
    parts = []
    for k, a in enumerate(azimuths):
        rho = rng.uniform(*radii)
        x, y = rho * np.cos(a), rho * np.sin(a)
        if k % 2 == 0:
            half = rng.uniform(0.1, 0.16)
            h = rng.uniform(0.2, 0.35)
            mesh = box((x - half, y - half, zg), (x + half, y + half, zg + h))
            albedo = textures.wood(seed + 30 + k, plank=0.08, ring=0.02, axes=(0, 2))
        else:
            mesh = cylinder((x, y), rng.uniform(0.08, 0.13), zg, zg + rng.uniform(0.25, 0.4))
            albedo = textures.glaze(seed + 30 + k, base=(0.35, 0.3, 0.25), band=(0.6, 0.25, 0.15), period=0.1)
        parts.append(Part(f"prop {k}", *mesh, albedo, "prop"))
    return parts


def _courtyard(seed: int, zg: float, half: float, height: float) -> list[Part]:
    w, z1 = half, zg + height
    corners = [(-w, -w), (w, -w), (w, w), (-w, w)]
    parts = []
    for k in range(4):
        (x0, y0), (x1, y1) = corners[k], corners[(k + 1) % 4]
        v, t = quad((x0, y0, zg), (x1, y1, zg), (x1, y1, z1), (x0, y0, z1))
        t = t[:, ::-1]  # facing the inside
        parts.append(Part(f"facade {k}", v, t, textures.facade(seed + 40 + k, triangle_normals(v, t), window=(0.5, 0.7),
                                                               floor_height=1.2, brick=k % 2 == 0), "backdrop"))
    return parts


def _ground_world(surface: Surface, seed: int) -> World:
    zg = float(surface.vertices[:, 2].min())
    g = 40.0
    parts = [_object_part(surface)]
    parts.append(Part("ground", *quad((-g, -g, zg), (g, -g, zg), (g, g, zg), (-g, g, zg)), textures.ground(seed + 20, 0.08, fade=0.01), "ground"))
    parts += _props(seed, zg, radii=(1.1, 1.4))
    parts += _courtyard(seed, zg, 10.0, 8.0)
    top = float(surface.vertices[:, 2].max())
    return World(parts, zg, grown_hull(surface.vertices[:, :2], 0.3), (zg - CROP_Z_MARGIN, top + CROP_Z_MARGIN), "ground")


def _sky_world(surface: Surface, seed: int) -> World:
    zg = float(surface.vertices[:, 2].min())
    radius = 100.0
    parts = [_object_part(surface)]
    meadow = textures.ground(seed + 50, 0.06, light=(0.45, 0.55, 0.3), dark=(0.3, 0.38, 0.18), fade=0.01)
    parts.append(Part("ground", *disc(radius * 1.001, zg), meadow, "ground"))
    parts.append(Part("sky", *dome(radius, zg), textures.sky(seed + 51, (0.0, 0.0, zg)), "backdrop", lit=False))
    top = float(surface.vertices[:, 2].max())
    return World(parts, zg, grown_hull(surface.vertices[:, :2], 0.3), (zg - CROP_Z_MARGIN, top + CROP_Z_MARGIN), "sky")


def _yard_world(surface: Surface, seed: int) -> World:
    zg = float(surface.vertices[:, 2].min())
    parts = [_object_part(surface)]
    parts.append(Part("ground", *quad((-60, -60, zg), (60, -60, zg), (60, 60, zg), (-60, 60, zg)),
                      textures.ground(seed + 60, 0.03, light=(0.55, 0.53, 0.5), dark=(0.3, 0.3, 0.3), fade=0.01), "ground"))
    rng = np.random.default_rng(seed + 61)
    count = 14
    for k in range(count):
        a = 2 * np.pi * (k + rng.uniform(0.2, 0.8)) / count
        rho = rng.uniform(2.0, 3.0)
        half = rng.uniform(0.25, 0.45, size=2)
        x, y = rho * np.cos(a), rho * np.sin(a)
        v, t = box((x - half[0], y - half[1], zg), (x + half[0], y + half[1], zg + rng.uniform(0.6, 1.3)))
        parts.append(Part(f"building {k}", v, t, textures.facade(seed + 62 + k, triangle_normals(v, t), brick=k % 3 == 0,
                                                                color=tuple(rng.uniform(0.5, 0.85, 3))), "prop"))
    parts.append(Part("sky", *dome(40.0, zg), textures.sky(seed + 90, (0.0, 0.0, zg)), "backdrop", lit=False))
    top = float(surface.vertices[:, 2].max())
    return World(parts, zg, grown_hull(surface.vertices[:, :2], 0.06), (zg - CROP_Z_MARGIN, top + CROP_Z_MARGIN), "yard")


ENVIRONMENTS = {"room": _room, "ground": _ground_world, "sky": _sky_world, "yard": _yard_world}


def make_environment(kind: str, surface: Surface, seed: int) -> World:
    """The object ``surface`` standing in environment ``kind`` (see the module docstring)."""
    if kind not in ENVIRONMENTS:
        raise DataError(f"unknown environment {kind!r}; expected one of {sorted(ENVIRONMENTS)}")
    return ENVIRONMENTS[kind](surface, seed)
