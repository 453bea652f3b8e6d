"""SuGaR level-set extraction, the ``poisson`` mesh extractor, as docs/methods/sugar.md §4 states it: level-set
points along each view's pixel rays, split into foreground and background, then screened Poisson per part.

The field (κ = 1) is d(x) = Σ_j o_j·exp(−½‖diag(1/s_j) R_jᵀ (x − μ_j)‖²) over the K = 16 centres nearest to the
pixel's hit point p, the squared norm clamped to [0, 1e8] and s to >= 1e-8 (docs/methods/sugar.md §5). Along the
ray x = p + t·v̂ each term is exactly quadratic in t, |a_j + t·b_j|² with a_j = diag(1/s_j)R_jᵀ(p − μ_j) and
b_j = diag(1/s_j)R_jᵀv̂, so a sample costs three numbers a neighbour. The outward normal is −∇d/‖∇d‖ =
normalize(Σ_j o_j G_j(x)·R_j diag(1/s_j)·y_j), y_j = diag(1/s_j)R_jᵀ(x − μ_j), analytically.
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Sequence
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree
from tqdm import tqdm

from gsbench.config.run_config import MeshConfig
from gsbench.data.camera import Camera
from gsbench.errors import ConfigError, import_open3d
from gsbench.geometry.depth import pixel_rays
from gsbench.mesh import MeshError
from gsbench.mesh.cleanup import to_trimesh
from gsbench.raster import RasterGaussians, RasterSettings, rasterize
from gsbench.raster.payload import quat_to_rotmat
from gsbench.signals import signals_deferred

# Open3D's screened Poisson on more than one thread crashes (SIGSEGV) at random when the cores are busy, and
# its mesh then depends on the thread count (Open3D issues 6828, 7229; PoissonRecon 298): one thread, always.
POISSON_THREADS = 1
MIN_OPACITY = 0.5  # docs/methods/sugar.md §4.1: Gaussians with opacity <= 0.5 are removed
KNN = 16  # neighbours of the density field
RAY_SAMPLES = 21  # n_points_in_range
RAY_SIGMAS = 3.0  # range_size: samples over ±3σ
ALPHA_MIN = 0.5  # a pixel "hits" the model when its rendered alpha is at least this
MAHALANOBIS_MAX = 1e8  # docs/methods/sugar.md §5
SCALE_MIN = 1e-8  # docs/methods/sugar.md §5
FOREGROUND_EXTENTS = 1.0  # foreground cube half-size, in cameras_extent
BACKGROUND_EXTENTS = 4.0  # background cube half-size, in cameras_extent
MIN_PART_POINTS = 100  # a part with fewer points is dropped
OUTLIER_NEIGHBOURS = 20  # open3d remove_statistical_outlier nb_neighbors
OUTLIER_STD_RATIO = 20.0  # and std_ratio
POISSON_SCALE = 1.1
MAX_POISSON_DEPTH = 10  # SuGaR's depth; the cap of the auto depth
CHUNK_PIXELS = 1 << 14  # pixels per crossing batch: 44 MB per (pixel, neighbour, sample) float64 array


@dataclass
class DensityField:
    """The κ = 1 density field of Gaussians (module docstring) with a KD-tree over their centres.

    means (N,3), inv_scaled = R diag(1/s) (N,3,3), rotations R (N,3,3), scales s (N,3) clamped at
    >= 1e-8, opacities (N,); float64.
    """

    means: torch.Tensor
    rotations: torch.Tensor
    scales: torch.Tensor
    inv_scaled: torch.Tensor
    opacities: torch.Tensor
    tree: object

    @classmethod
    def of(cls, gaussians: RasterGaussians) -> DensityField:
        means = gaussians.means.detach().to(torch.float64)
        rotations = quat_to_rotmat(torch.nn.functional.normalize(gaussians.quats.detach().to(torch.float64), dim=-1))
        scales = gaussians.scales.detach().to(torch.float64).clamp(min=SCALE_MIN)
        return cls(means, rotations, scales, rotations / scales[:, None, :],
                   gaussians.opacities.detach().to(torch.float64), cKDTree(means.numpy()))

    def neighbours(self, points: torch.Tensor) -> torch.Tensor:
        """(P, min(16, N)) indices of the centres nearest to ``points`` (P,3), nearest first."""
        k = min(KNN, len(self.means))
        with signals_deferred():
            _, idx = self.tree.query(points.numpy(), k=k, workers=-1)
        return torch.as_tensor(np.asarray(idx).reshape(len(points), k), dtype=torch.int64)


def _gaussian_terms(squared: torch.Tensor, opacities: torch.Tensor) -> torch.Tensor:
    """o·exp(−½ m²) with m² clamped to [0, 1e8] (docs/methods/sugar.md §5)."""
    return opacities * torch.exp(-0.5 * squared.clamp(0.0, MAHALANOBIS_MAX))


def level_crossings(field: DensityField, hits: torch.Tensor, directions: torch.Tensor, level: float
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """First crossings of d = ``level`` along the rays ``hits`` + t·``directions`` (P,3 each, unit
    directions), t in ±3σ around each hit (docs/methods/sugar.md §4.2).

    Returns (points (Q,3), outward unit normals −∇d/‖∇d‖ (Q,3), the (P,) bool mask of the rays kept).
    """
    idx = field.neighbours(hits)
    offsets = hits[:, None, :] - field.means[idx]
    inv_scaled = field.inv_scaled[idx]
    a = torch.einsum("pkc,pkcd->pkd", offsets, inv_scaled)
    b = torch.einsum("pc,pkcd->pkd", directions, inv_scaled)
    aa, ab, bb = (a * a).sum(-1), (a * b).sum(-1), (b * b).sum(-1)
    opacities = field.opacities[idx]
    owner = idx.gather(1, _gaussian_terms(aa, opacities).argmax(1, keepdim=True)).squeeze(1)
    local = torch.einsum("pji,pj->pi", field.rotations[owner], directions)
    sigma = (field.scales[owner] * local).norm(dim=-1)
    t = torch.linspace(-RAY_SIGMAS, RAY_SIGMAS, RAY_SAMPLES, dtype=hits.dtype)[None, :] * sigma[:, None]
    squared = aa[..., None] + 2.0 * ab[..., None] * t[:, None, :] + bb[..., None] * t[:, None, :] ** 2
    density = _gaussian_terms(squared, opacities[..., None]).sum(1)
    above = density > level
    first = above.to(torch.int8).argmax(1)
    keep = above.any(1) & (first > 0) & (density[:, 0] < level)
    rows, k = torch.nonzero(keep).flatten(), first[keep]
    d0, d1 = density[rows, k - 1], density[rows, k]
    t0, t1 = t[rows, k - 1], t[rows, k]
    t_level = t0 + (level - d0) / (d1 - d0) * (t1 - t0)
    local = a[rows] + t_level[:, None, None] * b[rows]
    weights = _gaussian_terms((local * local).sum(-1), opacities[rows])
    direction = (weights[..., None] * torch.einsum("pkcd,pkd->pkc", inv_scaled[rows], local)).sum(1)
    norm = direction.norm(dim=-1)
    good = torch.isfinite(norm) & (norm > 0)
    keep[rows[~good]] = False
    points = hits[rows] + t_level[:, None] * directions[rows]
    return points[good], direction[good] / norm[good, None], keep


def view_points(field: DensityField, gaussians: RasterGaussians, camera: Camera, settings: RasterSettings, *,
                kernel: str, depth_output: str, level: float, mask: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(points, normals, rgb, pixel footprints z/f) of one view's level crossings (docs/methods/sugar.md §4.2)."""
    out = rasterize(gaussians, camera, kernel=kernel, outputs=tuple(sorted({depth_output, "alpha", "rgb"})),
                    settings=settings)
    depth = getattr(out, depth_output).detach().to(torch.float64)
    hit = (out.alpha.detach() >= ALPHA_MIN) & torch.isfinite(depth) & (depth > 0)
    if mask is not None:
        hit &= torch.as_tensor(np.asarray(mask, dtype=bool))
    R = torch.as_tensor(camera.R, dtype=torch.float64)
    rays = pixel_rays(camera, torch.float64)[hit] @ R  # world directions of the camera rays (z = 1)
    centre = torch.as_tensor(camera.center, dtype=torch.float64)
    hits = centre + depth[hit][:, None] * rays
    directions = torch.nn.functional.normalize(rays, dim=-1)
    colors = out.rgb.detach().clamp(0, 1).to(torch.float64)[hit]
    points, normals, rgb = [], [], []
    for start in range(0, len(hits), CHUNK_PIXELS):
        part = slice(start, start + CHUNK_PIXELS)
        p, n, keep = level_crossings(field, hits[part], directions[part], level)
        points.append(p)
        normals.append(n)
        rgb.append(colors[part][keep])
    points = torch.cat(points) if points else torch.zeros(0, 3, dtype=torch.float64)
    normals = torch.cat(normals) if normals else torch.zeros(0, 3, dtype=torch.float64)
    rgb = torch.cat(rgb) if rgb else torch.zeros(0, 3, dtype=torch.float64)
    z = (points - centre) @ R[2]
    footprint = z / (0.5 * (camera.fx + camera.fy))
    return points.numpy(), normals.numpy(), rgb.numpy(), footprint.numpy()


def auto_poisson_depth(points: np.ndarray, footprints: np.ndarray) -> int:
    """The smallest depth with 1.1·(bounding-box side)/2^depth <= median footprint, in [1, 10]."""
    side = float(np.ptp(points, axis=0).max())
    footprint = float(np.median(footprints))
    if not (side > 0 and footprint > 0):
        return 1
    return int(min(MAX_POISSON_DEPTH, max(1, math.ceil(math.log2(POISSON_SCALE * side / footprint)))))


@contextmanager
def _silenced_stderr():
    """Send file descriptor 2 to /dev/null: open3d's PoissonRecon writes hundreds of harmless
    "getValue assumes leaf node" warnings straight to stderr, past open3d's verbosity setting."""
    sys.stderr.flush()
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def poisson_surface(points: np.ndarray, normals: np.ndarray, colors: np.ndarray, *, depth: int,
                    density_quantile: float, max_triangles: int):
    """Outlier removal, screened Poisson, density-quantile trim, decimation, clean-up (docs/methods/sugar.md §4.4)."""
    o3d = import_open3d()
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.normals = o3d.utility.Vector3dVector(normals)
    cloud.colors = o3d.utility.Vector3dVector(colors)
    cloud, _ = cloud.remove_statistical_outlier(nb_neighbors=OUTLIER_NEIGHBOURS, std_ratio=OUTLIER_STD_RATIO)
    with _silenced_stderr():
        mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            cloud, depth=depth, width=0, scale=POISSON_SCALE, linear_fit=False, n_threads=POISSON_THREADS)
    densities = np.asarray(densities)
    if density_quantile > 0 and len(densities):
        mesh.remove_vertices_by_mask(densities < np.quantile(densities, density_quantile))
    if 0 < max_triangles < len(mesh.triangles):
        mesh = mesh.simplify_quadric_decimation(target_number_of_triangles=int(max_triangles))
    mesh.remove_degenerate_triangles()
    mesh.remove_duplicated_triangles()
    mesh.remove_duplicated_vertices()
    mesh.remove_non_manifold_edges()
    mesh.remove_unreferenced_vertices()
    return mesh


def _check(cfg: MeshConfig) -> None:
    """ConfigError for a level or Poisson setting out of range."""
    if not 0.0 < cfg.level < 1.0:
        raise ConfigError(f"mesh.level must be in (0, 1) for the poisson extractor (SuGaR: 0.3), got {cfg.level}")
    if cfg.poisson_depth < 0 or not 0.0 <= cfg.poisson_density_quantile < 1.0 or cfg.poisson_points < 1:
        raise ConfigError(f"poisson extractor needs mesh.poisson_depth >= 0 (0 = auto), 0 <= "
                        f"mesh.poisson_density_quantile < 1 and mesh.poisson_points >= 1; got {cfg.poisson_depth}, "
                        f"{cfg.poisson_density_quantile}, {cfg.poisson_points}")


def levelset_mesh(gaussians: RasterGaussians, cameras: Sequence[Camera], settings: RasterSettings, cfg: MeshConfig,
                  *, kernel: str, depth_output: str, centre: np.ndarray, extent: float,
                  masks: Sequence[np.ndarray] | None = None, seed: int = 0):
    """SuGaR's coarse mesh of ``gaussians`` seen by ``cameras`` as a ``trimesh.Trimesh`` (module docstring).

    ``settings``/``kernel`` render the hit depths (``depth_output``: ``depth`` or ``median_depth``);
    ``centre``/``extent`` place the foreground and background cubes; ``masks`` (one per camera or
    None) restrict the pixels; ``seed`` drives the per-view subsampling.
    """
    _check(cfg)
    keep = gaussians.opacities.detach() > MIN_OPACITY
    context = (f"(level={cfg.level}, views={len(cameras)}, Gaussians with opacity > {MIN_OPACITY}: "
               f"{int(keep.sum())} of {len(gaussians)}, poisson_depth={cfg.poisson_depth}, "
               f"density_quantile={cfg.poisson_density_quantile})")
    if not bool(keep.any()):
        raise MeshError(f"poisson extraction has no Gaussian to mesh {context}; train longer")
    kept = gaussians.map(lambda t: t.detach()[keep])
    field = DensityField.of(kept)
    per_view = cfg.poisson_points // max(len(cameras), 1) + 1
    rng = np.random.default_rng(seed)
    parts = []
    for i, camera in enumerate(tqdm(cameras, desc="extract", unit="view", disable=None, leave=False)):
        found = view_points(field, kept, camera, settings, kernel=kernel, depth_output=depth_output,
                            level=cfg.level, mask=None if masks is None else masks[i])
        if len(found[0]) > per_view:
            chosen = np.sort(rng.choice(len(found[0]), per_view, replace=False))
            found = tuple(a[chosen] for a in found)
        parts.append(found)
    points, normals, colors, footprints = (np.concatenate([p[j] for p in parts]) for j in range(4))
    reach = np.abs(points - np.asarray(centre)).max(1) / extent
    o3d = import_open3d()
    mesh = o3d.geometry.TriangleMesh()
    for part in (reach <= FOREGROUND_EXTENTS, (reach > FOREGROUND_EXTENTS) & (reach <= BACKGROUND_EXTENTS)):
        if part.sum() < MIN_PART_POINTS:
            continue
        depth = cfg.poisson_depth or auto_poisson_depth(points[part], footprints[part])
        mesh += poisson_surface(points[part], normals[part], colors[part], depth=depth,
                                density_quantile=cfg.poisson_density_quantile, max_triangles=cfg.poisson_triangles)
    if len(mesh.triangles) == 0:
        raise MeshError(f"poisson extraction produced an empty mesh from {len(points)} level-set points {context}; "
                        "check that the level is crossed (train longer, or lower mesh.level)")
    if not np.isfinite(np.asarray(mesh.vertices)).all():
        raise MeshError(f"poisson extraction produced non-finite vertices {context}")
    return to_trimesh(mesh)
