"""Procedural objects for the DTU-like scenes: closed, outward-oriented, one-component triangle meshes.

Each builder returns ``(vertices, triangles)`` in its own units with the object standing on z = 0
(its lowest points exactly at z = 0); `shapes.make_surface` moves them into the object frame.

- ``stool``: a round seat on four splayed legs joined by rungs (thin parts: legs 0.036 and rungs
  0.022 of the object size thick, 3.6 mm and 2.2 mm at 100 mm), the feet cut flat by z = 0.
- ``bowl``: a thick hemispherical shell (a deep bowl, concave inside) on a foot ring, with a loop
  handle (a torus) on one side: concavity plus a through hole.
- ``vase``: a surface of revolution ``r(z)`` (belly, neck, lip), closed by flat discs at the bottom
  and the top; exact parametric mesh (no marching cubes).
- ``pebbles``: two ellipsoids blended by a smooth minimum, cut flat at z = 0 (a smooth shape).
- ``yard``: disjoint building blocks (boxes, a thin wall, a stepped tower; several closed components).
- ``blocks``: an exact polyhedron with sharp edges: a stepped stack of prisms (square plinth, a
  five-point star, a small square tower), see `stepped_prisms`.
- Glassware (the glass scenes; `revolved_shell`): ``orb``, a solid ball (thick glass) resting on z = 0;
  ``wineglass``, a cup with walls 0.02 of its height on a solid stem and a foot disc (thin walls and a
  thick stem); ``bottle``, a thin-walled (0.022) bottle with a shoulder, a neck and an open mouth.

Signed-distance shapes (stool, bowl, pebbles) are meshed by `sdf_mesh`: the SDF sampled on a grid
of ``voxel`` spacing whose nodes sit half a voxel off z = 0 (so a flat cut at z = 0 is reproduced
exactly by the linear interpolation; for speed the SDF is evaluated exactly only in a narrow band,
elsewhere a node takes the value of its nearest node on a 4x coarser grid, whose sign is right
there, so the mesh equals the full evaluation's), `skimage.measure.marching_cubes` at level 0,
edges shorter than 0.001 voxel collapsed (`_collapse_short_edges`), the largest connected component
kept, triangles flipped when the signed volume is negative.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from skimage.measure import marching_cubes

from gsbench.data.synthetic.primitives import box, merge
from gsbench.errors import DataError

SDF_VOXEL = 0.004
COARSE = 4
MIN_EDGE = 1e-3  # x voxel


def sdf_mesh(sdf, lo, hi, voxel: float = SDF_VOXEL) -> tuple[np.ndarray, np.ndarray]:
    """Marching-cubes mesh of ``sdf(points (N,3)) -> (N,)`` (negative inside) over the box [lo, hi]."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    lo = lo.copy()
    lo[2] = -(np.ceil(-lo[2] / voxel - 0.5) + 0.5) * voxel  # nodes at z = (k + 0.5) voxel
    shape = tuple(int(np.ceil((hi[i] - lo[i]) / voxel / COARSE)) * COARSE + 1 for i in range(3))
    coarse_axes = [lo[i] + COARSE * voxel * np.arange((shape[i] - 1) // COARSE + 1) for i in range(3)]
    cx, cy, cz = np.meshgrid(*coarse_axes, indexing="ij")
    coarse = sdf(np.stack([cx.ravel(), cy.ravel(), cz.ravel()], axis=1)).reshape(cx.shape)
    # fine node value = its nearest coarse node's value unless that is within the band where the sign
    # could differ (|d| < 2 x the half coarse-cell diagonal, SDFs are 1-Lipschitz): there, the exact SDF
    index = [(np.arange(n) + COARSE // 2) // COARSE for n in shape]
    grid = coarse[np.ix_(*index)].astype(np.float32)
    near = np.argwhere(np.abs(grid) < COARSE * voxel * np.sqrt(3))
    for start in range(0, len(near), 1_000_000):
        chunk = near[start:start + 1_000_000]
        grid[chunk[:, 0], chunk[:, 1], chunk[:, 2]] = sdf(lo + voxel * chunk)
    if grid[0].min() <= 0 or grid[-1].min() <= 0 or grid[:, 0].min() <= 0 or grid[:, -1].min() <= 0 \
            or grid[:, :, 0].min() <= 0 or grid[:, :, -1].min() <= 0:
        raise DataError("sdf_mesh: the shape touches the grid boundary; fix: enlarge the bounds")
    verts, faces, _, _ = marching_cubes(grid, 0.0, spacing=(voxel,) * 3, allow_degenerate=False)
    mesh = _collapse_short_edges(trimesh.Trimesh(verts + lo, faces, process=True), MIN_EDGE * voxel)
    parts = mesh.split(only_watertight=False)
    mesh = max(parts, key=lambda m: len(m.faces))
    if mesh.volume < 0:
        mesh.invert()
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def _collapse_short_edges(mesh, min_edge: float):
    """Merge the ends of edges shorter than ``min_edge`` (marching cubes puts vertices arbitrarily close
    together where the surface passes near a grid node; written as float32 PLY far from the origin
    they would coincide and break the mesh) and drop the triangles that become degenerate."""
    edges = mesh.edges_unique[mesh.edges_unique_length < min_edge]
    if len(edges) == 0:
        return mesh
    n = len(mesh.vertices)
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    counts = np.bincount(labels)
    vertices = np.zeros((labels.max() + 1, 3))
    np.add.at(vertices, labels, mesh.vertices)
    faces = labels[mesh.faces]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    return trimesh.Trimesh(vertices / counts[:, None], faces[keep], process=True)


def _capsule(p, a, b, radius):
    a, b = np.asarray(a, float), np.asarray(b, float)
    ab = b - a
    t = np.clip((p - a) @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * ab), axis=1) - radius


def _rounded_cylinder(p, centre, radius, half_height, rounding):
    q = p - np.asarray(centre, float)
    d = np.stack([np.hypot(q[:, 0], q[:, 1]) - radius + rounding, np.abs(q[:, 2]) - half_height + rounding], axis=1)
    return np.minimum(d.max(axis=1), 0.0) + np.linalg.norm(np.maximum(d, 0.0), axis=1) - rounding


def _smin(a, b, k):
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


def stool():
    seat_z, seat_r, leg_r, rung_r = 0.6, 0.32, 0.018, 0.011
    angles = np.radians([45.0, 135.0, 225.0, 315.0])
    tops = [np.array([0.22 * np.cos(a), 0.22 * np.sin(a), seat_z]) for a in angles]
    feet = [np.array([0.3 * np.cos(a), 0.3 * np.sin(a), -0.05]) for a in angles]

    def leg_point(k, z):
        s = (z - feet[k][2]) / (tops[k][2] - feet[k][2])
        return feet[k] + s * (tops[k] - feet[k])

    def sdf(p):
        d = _rounded_cylinder(p, (0, 0, seat_z), seat_r, 0.025, 0.01)
        for k in range(4):
            d = np.minimum(d, _capsule(p, feet[k], tops[k], leg_r))
            j = (k + 1) % 4
            z = 0.22 if k % 2 == 0 else 0.3
            d = np.minimum(d, _capsule(p, leg_point(k, z), leg_point(j, z), rung_r))
        return np.maximum(d, -p[:, 2])  # feet cut flat at z = 0

    return sdf_mesh(sdf, (-0.36, -0.36, -0.02), (0.36, 0.36, 0.66))


def bowl():
    radius, wall = 0.45, 0.035
    centre = np.array([0.0, 0.0, radius + 0.05])
    top = centre[2] + 0.08

    def sdf(p):
        rho = np.linalg.norm(p - centre, axis=1)
        shell = np.maximum(np.abs(rho - (radius - wall / 2)) - wall / 2, p[:, 2] - top)
        foot = np.maximum(np.abs(np.hypot(p[:, 0], p[:, 1]) - 0.17) - 0.03, p[:, 2] - 0.12)
        q = p - np.array([radius + 0.06, 0.0, centre[2] - 0.02])
        torus = np.hypot(np.hypot(q[:, 0], q[:, 2]) - 0.1, q[:, 1]) - 0.022
        d = np.minimum(np.minimum(shell, foot), torus)
        cavity = np.maximum(rho - (radius - wall), p[:, 2] - top - 1.0)
        return np.maximum(np.maximum(d, -cavity), -p[:, 2])

    return sdf_mesh(sdf, (-0.5, -0.5, -0.02), (0.7, 0.5, 0.62), voxel=0.005)


def pebbles():
    def sdf(p):
        def ellipsoid(c, r):
            q = (p - np.asarray(c, float)) / np.asarray(r, float)
            return (np.linalg.norm(q, axis=1) - 1.0) * min(r)

        d = _smin(ellipsoid((0, 0, 0.2), (0.45, 0.34, 0.26)), ellipsoid((0.06, 0.02, 0.52), (0.26, 0.22, 0.17)), 0.12)
        return np.maximum(d, -p[:, 2])

    return sdf_mesh(sdf, (-0.5, -0.4, -0.02), (0.5, 0.4, 0.75), voxel=0.006)


def vase(n_theta: int = 256, n_z: int = 240):
    height = 1.0
    z = np.linspace(0.0, height, n_z)
    r = 0.16 + 0.14 * np.exp(-((z - 0.35) / 0.22) ** 2) - 0.06 * np.exp(-((z - 0.8) / 0.1) ** 2) + 0.05 * np.clip((z - 0.88) / 0.12, 0, 1) ** 2
    theta = np.linspace(0.0, 2 * np.pi, n_theta, endpoint=False)
    ring = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    vertices = np.concatenate([
        np.column_stack([np.repeat(r, n_theta)[:, None] * np.tile(ring, (n_z, 1)), np.repeat(z, n_theta)]),
        [[0.0, 0.0, 0.0], [0.0, 0.0, height]],
    ])
    bottom, top = n_z * n_theta, n_z * n_theta + 1
    i = np.arange(n_theta)
    j = (i + 1) % n_theta
    faces = []
    for k in range(n_z - 1):
        a, b, c, d = k * n_theta + i, k * n_theta + j, (k + 1) * n_theta + j, (k + 1) * n_theta + i
        faces += [np.stack([a, b, c], 1), np.stack([a, c, d], 1)]
    faces.append(np.stack([np.full(n_theta, bottom), j, i], 1))
    last = (n_z - 1) * n_theta
    faces.append(np.stack([np.full(n_theta, top), last + i, last + j], 1))
    return vertices, np.concatenate(faces).astype(np.int64)


def revolved_shell(profile: np.ndarray, half_wall: float):
    """SDF of the shell of half-thickness ``half_wall`` around a profile curve (M,2) of (radius, z) points
    revolved about the z axis: distance from (√(x² + y²), z) to the polyline, minus ``half_wall``."""
    a, b = profile[:-1], profile[1:]

    def sdf(p):
        q = np.column_stack([np.hypot(p[:, 0], p[:, 1]), p[:, 2]])
        best = np.full(len(q), np.inf)
        for start, end in zip(a, b):
            e = end - start
            s = np.clip(((q - start) @ e) / max(float(e @ e), 1e-30), 0.0, 1.0)
            best = np.minimum(best, np.linalg.norm(q - start - s[:, None] * e, axis=1))
        return best - half_wall

    return sdf


def orb(subdivisions: int = 5):
    """A ball of radius 0.5 touching z = 0 (icosphere, 20 480 triangles)."""
    ball = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.5)
    return np.asarray(ball.vertices) + np.array([0.0, 0.0, 0.5]), np.asarray(ball.faces, dtype=np.int64)


def wineglass():
    wall = 0.02
    z = np.linspace(0.0, 1.0, 41)
    cup = np.column_stack([0.3 * np.sin(np.pi / 2 * np.clip(z / 0.45, 0, 1)) - 0.04 * np.clip((z - 0.45) / 0.55, 0, 1) ** 2,
                           0.42 + 0.55 * z])
    cup_sdf = revolved_shell(cup, wall / 2)
    foot_sdf = revolved_shell(np.array([[0.0, 0.012], [0.26, 0.012]]), 0.012)

    def sdf(p):
        stem = np.maximum(np.hypot(p[:, 0], p[:, 1]) - 0.028, np.abs(p[:, 2] - 0.22) - 0.21)
        return np.maximum(np.minimum(np.minimum(cup_sdf(p), foot_sdf(p)), stem), -p[:, 2])

    return sdf_mesh(sdf, (-0.34, -0.34, -0.02), (0.34, 0.34, 1.0))


def bottle():
    z = np.linspace(0.0, 1.0, 61)
    radius = np.where(z < 0.55, 0.24, np.where(z < 0.78, 0.07 + 0.17 * (1 + np.cos(np.pi * (z - 0.55) / 0.23)) / 2, 0.07))
    profile = np.vstack([[0.0, 0.011], np.column_stack([radius, 0.011 + 0.96 * z])])
    return sdf_mesh(revolved_shell(profile, 0.011), (-0.28, -0.28, -0.02), (0.28, 0.28, 1.01))


def _radial(polygon: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Points where rays from the origin at ``angles`` leave a polygon star-shaped about the origin."""
    a = polygon
    b = np.roll(polygon, -1, axis=0)
    d = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    out = np.empty((len(angles), 2))
    for m, ray in enumerate(d):
        best = None
        for p, q in zip(a, b):
            e = q - p
            den = ray[0] * (-e[1]) + ray[1] * e[0]
            if abs(den) < 1e-15:
                continue
            t = (p[0] * (-e[1]) + p[1] * e[0]) / den  # ray t = p + s e
            s = (ray[0] * p[1] - ray[1] * p[0]) / den
            if t > 0 and -1e-12 <= s <= 1 + 1e-12 and (best is None or t < best):
                best = t
        out[m] = best * ray
    return out


def stepped_prisms(levels: list[tuple[np.ndarray, float, float]]) -> tuple[np.ndarray, np.ndarray]:
    """Exact union of stacked prisms: ``levels`` = [(polygon (M,2) CCW, z_bottom, z_top), ...], each
    polygon star-shaped about the origin and strictly inside the one below, z_top of one level =
    z_bottom of the next. All polygons are resampled at the union of their vertex angles (adding
    collinear vertices only), so consecutive rings correspond ray by ray: the side walls are quads
    between a ring at z_bottom and z_top, the step between two levels is a ring of quads between the
    outer and inner polygon, and the bottom and top are fans about the axis."""
    angles = np.unique(np.concatenate([np.mod(np.arctan2(p[:, 1], p[:, 0]), 2 * np.pi) for p, _, _ in levels]))
    angles = angles[np.concatenate([[True], np.diff(angles) > 1e-9])]  # one angle per direction
    if 2 * np.pi - angles[-1] + angles[0] <= 1e-9:
        angles = angles[:-1]
    rings = [_radial(p, angles) for p, _, _ in levels]
    n = len(angles)
    vertices, faces = [], []

    def ring(k, z):
        vertices.append(np.column_stack([rings[k], np.full(n, z)]))
        return (len(vertices) - 1) * n

    i = np.arange(n)
    j = (i + 1) % n
    starts = []
    for k, (_, z0, z1) in enumerate(levels):
        lo, hi = ring(k, z0), ring(k, z1)
        faces += [np.stack([lo + i, lo + j, hi + j], 1), np.stack([lo + i, hi + j, hi + i], 1)]
        starts.append((lo, hi))
    for k in range(len(levels) - 1):
        outer, inner = starts[k][1], starts[k + 1][0]
        for a, b, c, d in zip(outer + i, outer + j, inner + j, inner + i):  # quad a b c d, facing +z
            pa, pb, pc, pd = (np.concatenate(vertices)[[a, b, c, d], :2])
            cross = lambda u, v, w: (v[0] - u[0]) * (w[1] - u[1]) - (v[1] - u[1]) * (w[0] - u[0])  # noqa: E731
            if cross(pa, pb, pc) > 0 and cross(pa, pc, pd) > 0:
                faces.append(np.array([[a, b, c], [a, c, d]]))
            else:
                faces.append(np.array([[a, b, d], [b, c, d]]))
    n_ring = sum(len(v) for v in vertices)
    bottom_z, top_z = levels[0][1], levels[-1][2]
    vertices.append(np.array([[0.0, 0.0, bottom_z], [0.0, 0.0, top_z]]))
    faces.append(np.stack([np.full(n, n_ring), starts[0][0] + j, starts[0][0] + i], 1))
    faces.append(np.stack([np.full(n, n_ring + 1), starts[-1][1] + i, starts[-1][1] + j], 1))
    return np.concatenate(vertices), np.concatenate(faces).astype(np.int64)


def star(points: int, outer: float, inner: float, phase: float = 0.0) -> np.ndarray:
    a = phase + np.pi * np.arange(2 * points) / points
    r = np.where(np.arange(2 * points) % 2 == 0, outer, inner)
    return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)


def square(half: float, phase: float = np.pi / 4) -> np.ndarray:
    a = phase + np.pi / 2 * np.arange(4)
    return np.sqrt(2) * half * np.stack([np.cos(a), np.sin(a)], axis=1)


def blocks():
    return stepped_prisms([(square(0.45), 0.0, 0.16), (star(5, 0.42, 0.19, np.pi / 2), 0.16, 0.52),
                           (square(0.12, np.pi / 4 + 0.3), 0.52, 0.8)])


def yard():
    """Building blocks of a yard (disjoint closed meshes standing on z = 0): three boxes, a wall and a
    stepped tower, within about [-0.5, 0.5] x [-0.4, 0.4]."""
    tower = stepped_prisms([(square(0.12), 0.0, 0.25), (square(0.08), 0.25, 0.45), (square(0.045), 0.45, 0.6)])
    tower = (tower[0] + np.array([0.28, 0.2, 0.0]), tower[1])
    return merge([box((-0.5, 0.02, 0.0), (-0.12, 0.4, 0.42)), box((0.1, -0.38, 0.0), (0.42, -0.08, 0.22)),
                  box((-0.45, -0.35, 0.0), (-0.3, -0.05, 0.3)), box((-0.2, -0.31, 0.0), (0.05, -0.28, 0.14)), tower])


BUILDERS = {"stool": stool, "bowl": bowl, "vase": vase, "pebbles": pebbles, "blocks": blocks, "yard": yard, "orb": orb,
            "wineglass": wineglass, "bottle": bottle}
