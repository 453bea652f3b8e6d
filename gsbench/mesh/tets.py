"""GOF tetrahedra mesh extraction, `tetra_mesh`, as docs/methods/gof.md §7.2–§7.4 states it: the centre and the 8
corners ``μ + R(q)·(3·s_eff ⊙ c)``, ``c ∈ {−1, 1}³``, of every Gaussian seen by a camera; their Delaunay
tetrahedralisation; marching tetrahedra on GOF's "SDF" ``level − O(x)`` (positive = free space), then
``bisection_steps`` bisections of every crossing edge, the vertex the final interval's midpoint.

Marching and bisection read only the field's sign, so points are classified by `OpacityField.below`, exact and
with early exits. scipy's Qhull gives the triangulation GOF's CGAL does, up to ties between cospherical points.
``MAX_POINTS`` (2 000 000 points) bounds Delaunay's memory, about 2.8 kB a point (5.5 GB); ``CHUNK`` only paces
the progress bar. Measured costs: docs/methods/gof.md §7.6.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from scipy.spatial import Delaunay, QhullError
from tqdm import tqdm

from gsbench.data.camera import Camera
from gsbench.mesh import MeshError
from gsbench.raster import RasterGaussians, RasterSettings
from gsbench.raster.opacity_field import OpacityField
from gsbench.raster.payload import quat_to_rotmat

__all__ = [
    "CHUNK",
    "MAX_POINTS",
    "filtered_opacities",
    "filtered_scales",
    "frustum_mask",
    "marching_tetrahedra",
    "point_budget",
    "tetra_mesh",
    "tetra_points",
]

log = logging.getLogger(__name__)

BOX_SIGMAS = 3.0  # half-size of the box in units of s_eff (docs/methods/gof.md §7.2)
MAX_POINTS = 2_000_000  # tet points (9 per Gaussian) kept at most; ≈ 5.5 GB for the Delaunay
CHUNK = 1 << 18  # points per `OpacityField.below` call (32 B per point)
TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
BOX_CORNERS = np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])


def filtered_scales(g: RasterGaussians) -> torch.Tensor:
    """(N,3) ``s_eff = sqrt(s² + σ_f²)`` (docs/methods/gof.md §2.3); ``s`` without a filter."""
    s = g.scales[:, :3].detach()
    if g.filter3d is None:
        return s
    return torch.sqrt(s * s + g.filter3d.detach().reshape(-1, 1))


def filtered_opacities(g: RasterGaussians) -> torch.Tensor:
    """(N,) ``o_eff = o · sqrt(Π s² / Π (s² + σ_f²))`` (docs/methods/gof.md §2.3)."""
    o = g.opacities.detach().reshape(-1)
    if g.filter3d is None:
        return o
    s2 = g.scales[:, :3].detach() ** 2
    return o * torch.sqrt(s2.prod(-1) / (s2 + g.filter3d.detach().reshape(-1, 1)).prod(-1))


def tetra_points(g: RasterGaussians) -> torch.Tensor:
    """(N, 9, 3) tet points per Gaussian: index 0 the centre μ, 1..8 the box corners
    ``μ + R(q)·(3·s_eff ⊙ c)``, ``c ∈ {−1, 1}³`` in `BOX_CORNERS` order (docs/methods/gof.md §7.2)."""
    means = g.means.detach()
    rot = quat_to_rotmat(F.normalize(g.quats.detach(), dim=-1))  # (N,3,3), columns = principal axes
    corners = torch.as_tensor(BOX_CORNERS, dtype=means.dtype)  # (8,3)
    local = BOX_SIGMAS * filtered_scales(g)[:, None, :] * corners[None]  # (N,8,3)
    world = means[:, None, :] + torch.einsum("nij,nkj->nki", rot, local)
    return torch.cat([means[:, None, :], world], 1)


def frustum_mask(points: np.ndarray, cameras: Sequence[Camera], near: float, far: float) -> np.ndarray:
    """(P,) bool: seen by at least one camera, i.e. ``near < z < far`` and ``u ∈ [0, W)``, ``v ∈ [0, H)``
    with ``(u, v) = (fx·x/z + cx, fy·y/z + cy)`` in camera space (docs/methods/gof.md §7.2)."""
    pts = np.asarray(points, dtype=np.float64)
    seen = np.zeros(len(pts), dtype=bool)
    for cam in cameras:
        xc = pts @ np.asarray(cam.R, dtype=np.float64).T + np.asarray(cam.t, dtype=np.float64)
        z = xc[:, 2]
        front = (z > near) & (z < far)
        zs = np.where(front, z, 1.0)
        u = cam.fx * xc[:, 0] / zs + cam.cx
        v = cam.fy * xc[:, 1] / zs + cam.cy
        seen |= front & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    return seen


def point_budget(seen: np.ndarray, priority: np.ndarray, max_points: int) -> np.ndarray:
    """``seen`` (N, 9) restricted to at most ``max_points`` points: whole Gaussians, taken by decreasing
    ``priority`` (N,) while their seen points fit; logs a warning when it drops any."""
    total = int(seen.sum())
    if total <= max_points:
        return seen
    order = np.argsort(-priority, kind="stable")
    fits = np.cumsum(seen[order].sum(1)) <= max_points
    keep = np.zeros(len(seen), dtype=bool)
    keep[order[fits]] = True
    log.warning(
        "tetra_mesh: %d tet points exceed max_points=%d; keeping the %d of %d Gaussians with the highest "
        "opacity (%d points). Raise max_points (≈ 2.8 kB of Delaunay memory per point) to keep all.",
        total, max_points, int(keep.sum()), len(seen), int(seen[keep].sum()),
    )
    return seen & keep[:, None]


def _free_space(field: OpacityField, points: np.ndarray, level: float, chunk: int, desc: str) -> np.ndarray:
    """(P,) bool ``O(x) < level`` (GOF's "SDF" ``level − O > 0``: free space) by `OpacityField.below`, in
    calls of at most ``chunk`` points."""
    pts = torch.as_tensor(np.asarray(points, dtype=np.float64))
    free = np.empty(len(pts), dtype=bool)
    for s in tqdm(range(0, len(pts), chunk), desc=desc, unit="chunk", disable=None, leave=False):
        free[s : s + chunk] = field.below(pts[s : s + chunk], level).numpy()
    return free


def _triangle_table() -> tuple[np.ndarray, np.ndarray]:
    """(16, 2, 3) local edge ids (into `TET_EDGES`) of the triangles of each sign case (bit v set = vertex
    v above the level) and (16,) triangle counts. One vertex apart from the other three: the triangle on
    its 3 edges; two and two (a, b | c, d): the quad ac-ad-bd-bc split into two triangles."""
    edge_id = {frozenset(e): k for k, e in enumerate(TET_EDGES.tolist())}
    table = np.zeros((16, 2, 3), dtype=np.int64)
    count = np.zeros(16, dtype=np.int64)
    for case in range(1, 15):
        up = [v for v in range(4) if case >> v & 1]
        down = [v for v in range(4) if not case >> v & 1]
        if len(up) == 2:
            (a, b), (c, d) = up, down
            quad = [edge_id[frozenset(p)] for p in ((a, c), (a, d), (b, d), (b, c))]
            table[case] = [quad[:3], [quad[0], quad[2], quad[3]]]
            count[case] = 2
        else:
            lone, others = (up[0], down) if len(up) == 1 else (down[0], up)
            table[case, 0] = [edge_id[frozenset((lone, w))] for w in others]
            count[case] = 1
    return table, count


TRIANGLE_TABLE, TRIANGLE_COUNT = _triangle_table()


def _crossing_faces(tets: np.ndarray, above: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique crossing edges (E, 2) (vertex pairs, sorted) and faces (F, 3) indexing them."""
    code = above[tets] @ np.array([1, 2, 4, 8])
    n_tri = TRIANGLE_COUNT[code]
    first, second = np.nonzero(n_tri >= 1)[0], np.nonzero(n_tri == 2)[0]
    tet_of = np.concatenate([first, second])
    local = np.concatenate([TRIANGLE_TABLE[code[first], 0], TRIANGLE_TABLE[code[second], 1]])  # (F,3)
    pairs = tets[tet_of[:, None, None], TET_EDGES[local]].astype(np.int64)  # (F,3,2) vertex ids
    n = np.int64(len(above))
    keys = pairs.min(-1) * n + pairs.max(-1)
    unique, faces = np.unique(keys.reshape(-1), return_inverse=True)
    return np.stack([unique // n, unique % n], 1), faces.reshape(-1, 3)


def _bisect(a: np.ndarray, b: np.ndarray, up_fn: Callable[[np.ndarray], np.ndarray], steps: int) -> np.ndarray:
    """Midpoints of the final intervals after ``steps`` halvings of the segments [a, b] (a above the
    level, b not): each step classifies all midpoints at once, ``up_fn`` (E,3) -> (E,) bool above, and
    keeps the half that still crosses."""
    for _ in tqdm(range(steps), desc="bisection", unit="step", disable=None, leave=False):
        mid = 0.5 * (a + b)
        up = np.asarray(up_fn(mid))[:, None]
        a, b = np.where(up, mid, a), np.where(up, b, mid)
    return 0.5 * (a + b)


def _crossing_edges(tets: np.ndarray, above: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(E,) above and (E,) below endpoint of every crossing edge, and the faces (F, 3) indexing the edges."""
    edges, faces = _crossing_faces(np.asarray(tets), above)
    up_first = above[edges[:, 0]]
    return np.where(up_first, edges[:, 0], edges[:, 1]), np.where(up_first, edges[:, 1], edges[:, 0]), faces


def _orient(vertices: np.ndarray, faces: np.ndarray, up_points: np.ndarray) -> np.ndarray:
    """Faces flipped so that their normal points to ``up_points[faces[:, 0]]`` (an above-level tet vertex,
    on the above side of the face's plane, which separates the tet's above and below vertices)."""
    v0, v1, v2 = (vertices[faces[:, k]] for k in range(3))
    normal = np.cross(v1 - v0, v2 - v0)
    flip = np.einsum("ij,ij->i", normal, up_points[faces[:, 0]] - v0) < 0
    return np.where(flip[:, None], faces[:, ::-1], faces)


def marching_tetrahedra(
    points: np.ndarray,
    tets: np.ndarray,
    values: np.ndarray,
    field_fn: Callable[[np.ndarray], np.ndarray] | None = None,
    level: float = 0.0,
    bisection_steps: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Triangle mesh ``(vertices (V,3) float64, faces (F,3) int64)`` of ``{values = level}`` on a tet mesh.

    ``points`` (P,3), ``tets`` (T,4) vertex ids, ``values`` (P,) the field at the points. A vertex counts
    as above when ``value > level``; a tet with both kinds is active and gives 1 or 2 triangles whose
    vertices lie on its crossing edges, one vertex per edge shared by all tets around it. Vertex on the
    crossing edge (a above, b below): with ``field_fn`` (maps (E,3) points to (E,) values) the midpoint of
    the interval left after ``bisection_steps`` bisections (docs/methods/gof.md §7.4, 8 steps); without it, the linear
    interpolation ``a + (level − f_a)/(f_b − f_a)·(b − a)`` (classic marching tetrahedra). Face normals
    point to the above side (for an SDF: outwards).
    """
    pts = np.asarray(points, dtype=np.float64)
    vals = np.asarray(values, dtype=np.float64).reshape(-1)
    if len(vals) != len(pts):
        raise ValueError(f"values must be (P,) = ({len(pts)},), got {vals.shape}")
    if field_fn is None and bisection_steps > 0:
        raise ValueError(f"bisection_steps={bisection_steps} needs a field_fn to evaluate midpoints")
    above = vals > level
    up_id, down_id, faces = _crossing_edges(tets, above)
    a, b = pts[up_id], pts[down_id]
    if field_fn is None:
        t = (level - vals[up_id]) / (vals[down_id] - vals[up_id])
        vertices = a + t[:, None] * (b - a)
    else:
        vertices = _bisect(a, b, lambda x: np.asarray(field_fn(x)) > level, bisection_steps)
    return vertices, _orient(vertices, faces, a)


def tetra_mesh(
    g: RasterGaussians,
    cameras: Sequence[Camera],
    settings: RasterSettings,
    *,
    kernel: str = "raymax",
    level: float = 0.5,
    bisection_steps: int = 8,
    max_points: int = MAX_POINTS,
    chunk: int = CHUNK,
):
    """GOF's tetrahedra mesh (module docstring, docs/methods/gof.md §7) of the opacity level set ``O(x) = level`` as a
    ``trimesh.Trimesh`` (normals point to free space). Raises `MeshError` naming the parameters when
    there is nothing to triangulate or the mesh is empty or non-finite."""
    cameras = list(cameras)
    n = len(g)
    info = {"gaussians": n, "cameras": len(cameras), "kernel": repr(kernel), "level": level,
            "bisection_steps": bisection_steps, "max_points": max_points, "near": f"{settings.near:.6g}",
            "far": f"{settings.far:.6g}"}

    def context() -> str:
        return "(" + ", ".join(f"{k}={v}" for k, v in info.items()) + ")"

    if n == 0 or not cameras:
        raise MeshError(f"tetra_mesh needs Gaussians and cameras {context()}")
    grid = tetra_points(g).to(torch.float64).numpy()  # (N,9,3)
    seen = frustum_mask(grid.reshape(-1, 3), cameras, settings.near, settings.far).reshape(n, 9)
    keep = point_budget(seen, filtered_opacities(g).to(torch.float64).numpy(), max_points)
    points = grid[keep]
    info["tet_points"] = len(points)
    if len(points) < 4:
        raise MeshError(f"tetra_mesh: fewer than 4 tet points inside the camera frustums {context()}; "
                        "check that the cameras look at the Gaussians")

    field = OpacityField(g, cameras, kernel=kernel, settings=settings)
    free = _free_space(field, points, level, chunk, "opacity field")
    info["free_points"] = f"{int(free.sum())}/{len(free)}"
    if free.all() or not free.any():
        raise MeshError(f"tetra_mesh: the opacity at every tet point is on one side of the level {context()}; "
                        "no surface crosses the tet grid: check that the Gaussians are trained (not transparent) "
                        "and seen by the cameras")
    try:
        tets = Delaunay(points).simplices
    except QhullError as exc:
        raise MeshError(f"tetra_mesh: Delaunay tetrahedralisation failed {context()}: {exc}") from exc
    info["tets"] = len(tets)
    up_id, down_id, faces = _crossing_edges(tets, free)
    info["crossing_edges"] = len(up_id)

    def up_fn(x: np.ndarray) -> np.ndarray:
        return _free_space(field, x, level, chunk, "bisection step")

    vertices = _bisect(points[up_id], points[down_id], up_fn, bisection_steps)
    faces = _orient(vertices, faces, points[up_id])
    if len(faces) == 0:
        raise MeshError(f"tetra_mesh produced an empty mesh {context()}; no tet crosses the level")
    if not np.isfinite(vertices).all():
        raise MeshError(f"tetra_mesh produced non-finite vertices {context()}")
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)

