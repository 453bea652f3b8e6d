"""TSDF fusion of rendered depth maps with open3d's ``VoxelBlockGrid`` (2DGS bounded TSDF, as
docs/methods/2dgs.md §6 states it: depth not integrated where not finite, below ``alpha_threshold`` or outside
the mask; lengths times ``scene_radius`` unless ``absolute``).

Not ``ScalableTSDFVolume``, which 2DGS calls: in open3d 0.20 it sizes its volume units from the depth divided
by a hard-coded 1000, so metric float depth integrates nothing. No half-pixel shift: open3d projects a voxel
to (u, v) with ``K`` and reads pixel ``(floor(u), floor(v))``, the cell [i, i + 1) whose centre gsbench puts
at i + 0.5 (a −0.5 shift of the principal point once moved every fused surface by half a pixel: Chamfer 0.55
against 0.37 mm on synthetic/spot; tests/test_mesh_tsdf.py fuses a tilted plane to catch it).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from gsbench.config.run_config import MeshConfig
from gsbench.data.camera import Camera
from gsbench.errors import import_open3d
from gsbench.mesh import MeshError
from gsbench.mesh.cleanup import keep_largest_clusters, to_trimesh

BLOCK_RESOLUTION = 16  # voxels per block side (open3d's default, = ScalableTSDFVolume's volume unit)
INITIAL_BLOCKS = 10_000  # initial hash-map capacity; it grows as needed
MIN_WEIGHT = 0.5  # open3d keeps weight > this: voxels observed at least once (legacy TSDF: weight != 0)


def fusion_parameters(cfg: MeshConfig, scene_radius: float) -> dict[str, float]:
    """Absolute ``voxel_size``, ``sdf_trunc``, ``depth_trunc`` (scene units) from ``cfg``."""
    scale = 1.0 if cfg.absolute else float(scene_radius)
    params = {"voxel_size": float(cfg.voxel_size) * scale, "sdf_trunc": float(cfg.sdf_trunc) * scale,
              "depth_trunc": float(cfg.depth_trunc) * scale}
    if not all(np.isfinite(v) and v > 0 for v in params.values()):
        raise MeshError(f"TSDF parameters must be positive and finite, got {params} (cfg voxel_size="
                        f"{cfg.voxel_size}, sdf_trunc={cfg.sdf_trunc}, depth_trunc={cfg.depth_trunc}, "
                        f"absolute={cfg.absolute}, scene_radius={scene_radius})")
    return params


def masked_depth(depth: np.ndarray, alpha: np.ndarray | None, mask: np.ndarray | None,
                 alpha_threshold: float) -> np.ndarray:
    """float32 depth with 0 where it must not be integrated (non-finite, low alpha, outside the mask)."""
    d = np.nan_to_num(np.asarray(depth, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    if alpha is not None:
        d[np.asarray(alpha) < alpha_threshold] = 0.0
    if mask is not None:
        d[~np.asarray(mask, dtype=bool)] = 0.0
    return np.ascontiguousarray(d)


def _check_view(i: int, camera: Camera, depth, color, alpha, mask) -> None:
    expected = (camera.height, camera.width)
    for what, arr in (("depth", depth), ("color", color), ("alpha", alpha), ("mask", mask)):
        if arr is not None and tuple(np.shape(arr)[:2]) != expected:
            raise MeshError(f"TSDF view {i} ({camera.name or 'unnamed'}): {what} has shape {np.shape(arr)}, "
                            f"expected {expected} (camera height x width)")


def tsdf_fusion(depths: Sequence[np.ndarray], cameras: Sequence[Camera], cfg: MeshConfig = MeshConfig(),
                scene_radius: float = 1.0, *, colors: Sequence[np.ndarray] | None = None,
                alphas: Sequence[np.ndarray] | None = None, masks: Sequence[np.ndarray] | None = None,
                alpha_threshold: float = 0.5):
    """Fuse HxW camera-z ``depths`` seen by ``cameras`` into a ``trimesh.Trimesh`` (module docstring).

    ``colors``: HxWx3 float in [0, 1] per view (vertex colours) or None; ``alphas``: HxW rendered
    alpha per view or None; ``masks``: HxW bool per view or None. Raises `MeshError` when the inputs
    do not match or the result is empty or non-finite.
    """
    o3d = import_open3d()
    n = len(cameras)
    for what, seq in (("depths", depths), ("colors", colors), ("alphas", alphas), ("masks", masks)):
        if seq is not None and len(seq) != n:
            raise MeshError(f"TSDF got {len(seq)} {what} for {n} cameras; give one per camera")
    p = fusion_parameters(cfg, scene_radius)
    o3c = o3d.core
    names, dtypes, channels = ["tsdf", "weight"], [o3c.float32, o3c.float32], [1, 1]
    if colors is not None:
        names, dtypes, channels = names + ["color"], dtypes + [o3c.float32], channels + [3]
    volume = o3d.t.geometry.VoxelBlockGrid(attr_names=names, attr_dtypes=dtypes, attr_channels=channels,
                                           voxel_size=p["voxel_size"], block_resolution=BLOCK_RESOLUTION,
                                           block_count=INITIAL_BLOCKS, device=o3c.Device("CPU:0"))
    fusion = {"depth_scale": 1.0, "depth_max": p["depth_trunc"],
              "trunc_voxel_multiplier": p["sdf_trunc"] / p["voxel_size"]}
    valid_pixels = 0
    for i, cam in enumerate(cameras):
        color = None if colors is None else colors[i]
        alpha = None if alphas is None else alphas[i]
        mask = None if masks is None else masks[i]
        _check_view(i, cam, depths[i], color, alpha, mask)
        depth = masked_depth(depths[i], alpha, mask, alpha_threshold)
        used = int(((depth > 0) & (depth <= p["depth_trunc"])).sum())
        if used == 0:
            continue
        K = np.array([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]])
        intrinsic = o3c.Tensor(K, o3c.float64)
        extrinsic = o3c.Tensor(cam.world_to_camera, o3c.float64)
        depth_image = o3d.t.geometry.Image(depth)
        try:
            blocks = volume.compute_unique_block_coordinates(depth_image, intrinsic, extrinsic, **fusion)
        except RuntimeError as exc:
            # open3d allocates blocks from a subsampled pixel grid: a view whose few valid pixels (a thin
            # plate seen edge-on) all fall between the samples touches no block and adds nothing.
            if "No block is touched" not in str(exc):
                raise
            continue
        valid_pixels += used
        if color is None:
            volume.integrate(blocks, depth_image, intrinsic, extrinsic, **fusion)
        else:
            rgb = o3d.t.geometry.Image(np.ascontiguousarray(np.clip(color, 0.0, 1.0), dtype=np.float32))
            volume.integrate(blocks, depth_image, rgb, intrinsic, extrinsic, **fusion)
    context = (f"(views={n}, integrated pixels={valid_pixels}, voxel_size={p['voxel_size']:.6g}, "
               f"sdf_trunc={p['sdf_trunc']:.6g}, depth_trunc={p['depth_trunc']:.6g}, absolute={cfg.absolute}, "
               f"scene_radius={scene_radius}, num_clusters={cfg.num_clusters}, alpha_threshold={alpha_threshold})")
    if valid_pixels == 0:
        raise MeshError(f"TSDF fusion has no depth to integrate {context}; check that the depth maps are camera z "
                        "in scene units, within depth_trunc, and that alpha/masks do not hide every pixel")
    try:
        mesh = volume.extract_triangle_mesh(weight_threshold=MIN_WEIGHT).to_legacy()
    except RuntimeError:  # open3d 0.20 fails to attach colours to an empty extraction
        mesh = o3d.geometry.TriangleMesh()
    mesh = keep_largest_clusters(mesh, cfg.num_clusters)
    vertices = np.asarray(mesh.vertices)
    if len(mesh.triangles) == 0:
        raise MeshError(f"TSDF fusion produced an empty mesh {context}; the surface may be thinner than a voxel "
                        "or seen by too few views: lower voxel_size or check the depth maps")
    if not np.isfinite(vertices).all():
        raise MeshError(f"TSDF fusion produced non-finite vertices {context}")
    return to_trimesh(mesh)
