"""Ground truth of synthetic scenes: even surface samples, SfM-like init points, DTU observation masks.

- `sample_surface`: evenly spaced surface points. Uniform random samples (trimesh, seeded) at about
  two per ``spacing``² are thinned to one per voxel of side ``1.5 spacing`` (open3d
  ``voxel_down_sample``, the voxel mean; 1.5 makes the median nearest-neighbour distance about
  ``spacing``) and snapped back onto the mesh (``RaycastingScene.compute_closest_points``), so every
  point lies on the surface (DTU's STL files are "0.2 mm reduced"; TnT GT is dense relative to tau).
- `visible_counts`: in how many views a point is seen: it projects inside the image onto an object
  pixel and its camera z is at most the rendered depth (``window`` x ``window`` maximum, 3 by
  default, so silhouette points count against a background of depth 0) plus a tolerance of three
  pixel footprints plus ``tol``. Depth maps of a whole environment have no background, so there
  ``window`` = 1 (a maximum would let points just behind a silhouette see past it); `seen_by_views`
  is that test, answering only "seen by >= k views" (faster).
- `sample_world_gt`: the GT surface of an object in its environment (``environment.py``): samples
  of the object (`voxel_samples`: per ``1.5 spacing`` voxel, the random surface sample nearest its
  centre, exactly on the mesh; without those within ``CONTACT`` object units above the ground, the faces it
  stands on) plus samples of the ground inside the GT polygon (`plane_samples`: one random point per
  ``1.5 spacing`` cell, the density of `sample_surface`) that are not inside the object
  (``RaycastingScene.compute_occupancy`` of the point lifted by ``CONTACT``).
- `sample_view_points`: SfM-like init points of an environment: per view, ``count / views`` rays
  through uniformly random image positions (seeded), their first hits plus Gaussian noise of std
  ``noise`` x the hit distance, with the albedo there as colour; so they cover what the images show
  (object, table, room) in proportion to its image area.
- `observation_mask`: the DTU ``ObsMask`` volume: voxels (size ``res``) holding a point seen by at
  least two views, dilated by ``dilation`` (Euclidean distance transform); ``BB`` = [min; max] of the
  grid, whose voxel (i, j, k) has centre ``BB[0] + res (i, j, k)`` (DTUeval-python indexing,
  ``round((p - BB[0]) / Res)``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from scipy.ndimage import distance_transform_edt, maximum_filter

from gsbench.data.camera import Camera
from gsbench.data.synthetic.primitives import Surface
from gsbench.errors import import_open3d

VOXEL_PER_SPACING = 1.5
CONTACT = 1e-4


def _trimesh(surface: Surface):
    return trimesh.Trimesh(surface.vertices, surface.triangles, process=False)


def sample_surface(surface: Surface, spacing: float, seed: int) -> np.ndarray:
    """Even surface samples about ``spacing`` apart, in the object frame (see the module docstring)."""
    o3d = import_open3d()
    mesh = _trimesh(surface)
    count = int(np.ceil(2.0 * mesh.area / spacing**2))
    dense, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    thin = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(dense)).voxel_down_sample(VOXEL_PER_SPACING * spacing)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(surface.vertices.astype(np.float32)), o3d.core.Tensor(surface.triangles.astype(np.uint32)))
    snapped = scene.compute_closest_points(o3d.core.Tensor(np.asarray(thin.points, dtype=np.float32)))["points"].numpy()
    return snapped.astype(np.float64)


def sample_init_points(surface: Surface, count: int, noise: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` random surface points with Gaussian noise (std ``noise``) and their albedo, like an SfM cloud."""
    mesh = _trimesh(surface)
    points, faces = trimesh.sample.sample_surface(mesh, count, seed=seed)
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[faces], points)[:, 1:]
    colors = surface.albedo(points, faces, bary)
    return points + np.random.default_rng(seed).normal(scale=noise, size=points.shape), colors


def visible_counts(points: np.ndarray, cameras: list[Camera], depths: list[np.ndarray], tol: float,
                   window: int = 3) -> np.ndarray:
    """Number of views in which each point is visible (see the module docstring)."""
    counts = np.zeros(len(points), dtype=np.int64)
    for cam, depth in zip(cameras, depths):
        pc = np.einsum("ij,nj->ni", cam.K @ cam.R, points) + cam.K @ cam.t  # einsum: skinny BLAS matmuls are slow
        z = pc[:, 2]
        ij = np.floor(pc[:, :2] / np.where(z > 0, z, 1.0)[:, None]).astype(np.int64)
        inside = (z > 0) & (ij[:, 0] >= 0) & (ij[:, 0] < cam.width) & (ij[:, 1] >= 0) & (ij[:, 1] < cam.height)
        near = (maximum_filter(depth, size=window) if window > 1 else depth)[ij[inside, 1], ij[inside, 0]]
        footprint = 3.0 * z[inside] / min(cam.fx, cam.fy)
        seen = (near > 0) & (z[inside] <= near + footprint + tol)
        counts[np.flatnonzero(inside)[seen]] += 1
    return counts


def sample_world_gt(world, spacing: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``(points (N,3), on_object (N,) bool)``: GT samples of a `World` in the object frame (module docstring)."""
    o3d = import_open3d()
    obj = world.object
    on_obj = voxel_samples(obj.vertices, obj.triangles, spacing, seed)
    on_obj = on_obj[on_obj[:, 2] >= world.ground_z + CONTACT]
    ground = plane_samples(world.gt_polygon.min(axis=0), world.gt_polygon.max(axis=0), world.ground_z, spacing, seed + 1)
    ground = ground[world.inside_gt_region(ground)]
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(obj.vertices.astype(np.float32)), o3d.core.Tensor(obj.triangles.astype(np.uint32)))
    lifted = (ground + np.array([0.0, 0.0, CONTACT])).astype(np.float32)
    ground = ground[scene.compute_occupancy(o3d.core.Tensor(lifted)).numpy() == 0]
    points = np.concatenate([on_obj, ground])
    return points, np.arange(len(points)) < len(on_obj)


def voxel_samples(vertices: np.ndarray, triangles: np.ndarray, spacing: float, seed: int) -> np.ndarray:
    """Even samples lying exactly on a mesh: area-uniform random points (about two per ``spacing``²,
    seeded), of which the one nearest the centre of each voxel of side ``1.5 spacing`` is kept (the
    density of `sample_surface`, without its voxel means and their snapping back onto the mesh)."""
    rng = np.random.default_rng(seed)
    a, b, c = (vertices[triangles[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    cumulative = np.cumsum(area)
    count = int(np.ceil(2.0 * cumulative[-1] / spacing**2))
    tri = np.minimum(np.searchsorted(cumulative, rng.uniform(0.0, cumulative[-1], count)), len(area) - 1)
    r1, r2 = np.sqrt(rng.uniform(size=count)), rng.uniform(size=count)
    points = (1 - r1)[:, None] * a[tri] + (r1 * (1 - r2))[:, None] * b[tri] + (r1 * r2)[:, None] * c[tri]
    scaled = (points - points.min(axis=0)) / (VOXEL_PER_SPACING * spacing)
    key = np.floor(scaled).astype(np.int64)
    code = (key[:, 0] * (key[:, 1].max() + 1) + key[:, 1]) * (key[:, 2].max() + 1) + key[:, 2]
    order = np.lexsort((np.sum((scaled - key - 0.5) ** 2, axis=1), code))
    first = order[np.concatenate([[True], np.diff(code[order]) != 0])]
    return points[np.sort(first)]


def plane_samples(lo, hi, z: float, spacing: float, seed: int) -> np.ndarray:
    """Samples of the rectangle [lo, hi] x {z}: one uniformly random point per square cell of side
    ``1.5 spacing`` (the density `sample_surface` gives a surface; exact on the plane, and fast)."""
    cell = VOXEL_PER_SPACING * spacing
    nx, ny = (int(np.ceil((h - l) / cell)) for l, h in zip(lo, hi))
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    xy = np.asarray(lo, dtype=np.float64) + cell * (np.stack([i.ravel(), j.ravel()], axis=1) + np.random.default_rng(seed).uniform(size=(i.size, 2)))
    xy = xy[(xy[:, 0] <= hi[0]) & (xy[:, 1] <= hi[1])]
    return np.column_stack([xy, np.full(len(xy), z)])


def sample_view_points(surface: Surface, cameras: list[Camera], count: int, noise: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``(points, colours)``: SfM-like points of what the views see (module docstring), object frame."""
    o3d = import_open3d()
    rng = np.random.default_rng(seed)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(surface.vertices.astype(np.float32)), o3d.core.Tensor(surface.triangles.astype(np.uint32)))
    per_view = int(np.ceil(count / len(cameras)))
    points, colours = [], []
    for cam in cameras:
        uv = rng.uniform(0.0, 1.0, size=(per_view, 2)) * [cam.width, cam.height]
        dirs = np.column_stack([uv, np.ones(per_view)]) @ (cam.R.T @ np.linalg.inv(cam.K)).T
        rays = np.concatenate([np.broadcast_to(cam.center, dirs.shape), dirs], axis=1).astype(np.float32)
        ans = {k: v.numpy() for k, v in scene.cast_rays(o3d.core.Tensor(rays)).items()}
        hit = np.isfinite(ans["t_hit"])
        exact = cam.center + ans["t_hit"][hit, None] * dirs[hit]
        colours.append(surface.albedo(exact, ans["primitive_ids"][hit].astype(np.int64), ans["primitive_uvs"][hit].astype(np.float64)))
        dist = ans["t_hit"][hit] * np.linalg.norm(dirs[hit], axis=1)
        points.append(exact + rng.normal(size=exact.shape) * (noise * dist)[:, None])
    return np.concatenate(points)[:count], np.concatenate(colours)[:count]


def seen_by_views(points: np.ndarray, cameras: list[Camera], depths: list[np.ndarray], tol: float, views: int) -> np.ndarray:
    """Whether each point is seen by at least ``views`` views: the test of `visible_counts` with
    ``window`` 1 (depth maps of a whole environment), in float32 with one BLAS product per view, and
    a point is no longer projected once it has been seen ``views`` times."""
    pending = np.arange(len(points))
    homogeneous = np.hstack([points, np.ones((len(points), 1))]).astype(np.float32)
    counts = np.zeros(len(points), dtype=np.int32)
    for cam, depth in zip(cameras, depths):
        P = (cam.K @ np.hstack([cam.R, cam.t[:, None]])).astype(np.float32)
        pc = homogeneous[pending] @ P.T
        z = pc[:, 2]
        front = z > 0
        zs = np.where(front, z, np.float32(1.0))
        i = np.floor(pc[:, 0] / zs).astype(np.int64)
        j = np.floor(pc[:, 1] / zs).astype(np.int64)
        inside = front & (i >= 0) & (i < cam.width) & (j >= 0) & (j < cam.height)
        near = np.zeros(len(pending), dtype=np.float32)
        near[inside] = depth[j[inside], i[inside]]
        seen = inside & (near > 0) & (z <= near + z * np.float32(3.0 / min(cam.fx, cam.fy)) + np.float32(tol))
        counts[pending[seen]] += 1
        pending = pending[counts[pending] < views]
    return counts >= views


def observation_mask(points: np.ndarray, observed: np.ndarray, res: float, dilation: float) -> tuple[np.ndarray, np.ndarray]:
    """``(ObsMask bool X×Y×Z, BB 2×3)`` from GT points and their observed flags (see the module docstring)."""
    margin = dilation + 2 * res
    lo = points[observed].min(axis=0) - margin
    hi = points[observed].max(axis=0) + margin
    shape = np.floor((hi - lo) / res).astype(np.int64) + 1
    occupied = np.zeros(shape, dtype=bool)
    g = np.round((points[observed] - lo) / res).astype(np.int64)
    occupied[g[:, 0], g[:, 1], g[:, 2]] = True
    mask = distance_transform_edt(~occupied) * res <= dilation
    return mask, np.stack([lo, lo + (shape - 1) * res])


def write_point_cloud(path: Path, points: np.ndarray) -> None:
    """Write (N,3) float64 points as a binary PLY (open3d; coordinates stay double precision)."""
    o3d = import_open3d()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)))
