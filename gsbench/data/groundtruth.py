"""Ground truth of synthetic scenes: even surface samples, SfM-like init points, DTU observation masks.

- `sample_surface`: evenly spaced surface points. Uniform random samples (trimesh, seeded) at about
  two per ``spacing``² are thinned to one per voxel of side ``1.5 spacing`` (open3d
  ``voxel_down_sample``, the voxel mean; 1.5 makes the median nearest-neighbour distance about
  ``spacing``) and snapped back onto the mesh (``RaycastingScene.compute_closest_points``), so every
  point lies on the surface (DTU's STL files are "0.2 mm reduced"; TnT GT is dense relative to tau).
- `visible_counts`: in how many views a point is seen: it projects inside the image onto an object
  pixel and its camera z is at most the rendered depth (3x3 maximum, so silhouette points count)
  plus a tolerance of three pixel footprints plus ``tol``.
- `observation_mask`: the DTU ``ObsMask`` volume: voxels (size ``res``) holding a point seen by at
  least two views, dilated by ``dilation`` (Euclidean distance transform); ``BB`` = [min; max] of the
  grid, whose voxel (i, j, k) has centre ``BB[0] + res (i, j, k)`` (DTUeval-python indexing,
  ``round((p - BB[0]) / Res)``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gsbench.data.camera import Camera
from gsbench.data.shapes import Surface
from gsbench.errors import import_open3d

VOXEL_PER_SPACING = 1.5


def _trimesh(surface: Surface):
    import trimesh  # noqa: PLC0415

    return trimesh.Trimesh(surface.vertices, surface.triangles, process=False)


def sample_surface(surface: Surface, spacing: float, seed: int) -> np.ndarray:
    """Even surface samples about ``spacing`` apart, in the object frame (see the module docstring)."""
    import trimesh  # noqa: PLC0415

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
    import trimesh  # noqa: PLC0415

    mesh = _trimesh(surface)
    points, faces = trimesh.sample.sample_surface(mesh, count, seed=seed)
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[faces], points)[:, 1:]
    colors = surface.albedo(points, faces, bary)
    return points + np.random.default_rng(seed).normal(scale=noise, size=points.shape), colors


def visible_counts(points: np.ndarray, cameras: list[Camera], depths: list[np.ndarray], tol: float) -> np.ndarray:
    """Number of views in which each point is visible (see the module docstring)."""
    from scipy.ndimage import maximum_filter  # noqa: PLC0415

    counts = np.zeros(len(points), dtype=np.int64)
    for cam, depth in zip(cameras, depths):
        pc = np.einsum("ij,nj->ni", cam.K @ cam.R, points) + cam.K @ cam.t  # einsum: skinny BLAS matmuls are slow
        z = pc[:, 2]
        ij = np.floor(pc[:, :2] / np.where(z > 0, z, 1.0)[:, None]).astype(np.int64)
        inside = (z > 0) & (ij[:, 0] >= 0) & (ij[:, 0] < cam.width) & (ij[:, 1] >= 0) & (ij[:, 1] < cam.height)
        near = maximum_filter(depth, size=3)[ij[inside, 1], ij[inside, 0]]
        footprint = 3.0 * z[inside] / min(cam.fx, cam.fy)
        seen = (near > 0) & (z[inside] <= near + footprint + tol)
        counts[np.flatnonzero(inside)[seen]] += 1
    return counts


def observation_mask(points: np.ndarray, observed: np.ndarray, res: float, dilation: float) -> tuple[np.ndarray, np.ndarray]:
    """``(ObsMask bool X×Y×Z, BB 2×3)`` from GT points and their observed flags (see the module docstring)."""
    from scipy.ndimage import distance_transform_edt  # noqa: PLC0415

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
