"""TSDF fusion (gsbench.mesh.tsdf) and mesh clean-up (gsbench.mesh.cleanup)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from gsbench.config.run_config import MeshConfig
from gsbench.data.loader import load_scene
from gsbench.data.synthetic.make import make_scene
from gsbench.mesh import MeshError
from gsbench.mesh.cleanup import canonical_order, keep_largest_clusters, to_trimesh
from gsbench.mesh.tsdf import fusion_parameters, tsdf_fusion

VOXEL = 0.02
CFG = MeshConfig(voxel_size=VOXEL, sdf_trunc=4 * VOXEL, depth_trunc=5.0, num_clusters=0)


@pytest.fixture(scope="module")
def spot(tmp_path_factory):
    """synthetic/spot at 96x72: scene, GT depth maps, GT points (normalised frame) seen by >= 1 view."""
    scene = load_scene(make_scene("synthetic/spot", out=tmp_path_factory.mktemp("scenes") / "spot", res=(96, 72)))
    depths = [np.load(scene.gt.depth_maps / f"{Path(name).stem}.npy") for name in scene.image_names]
    stl = scene.gt.root / "Points" / "stl" / f"stl{scene.gt.scan:03d}_total.ply"
    points = scene.normalisation.invert(np.asarray(trimesh.load(stl).vertices))[::5]
    seen = np.zeros(len(points), dtype=bool)
    for cam, depth in zip(scene.cameras, depths):
        uv, z = cam.project(points)
        pix = np.floor(uv).astype(int)
        inside = (pix[:, 0] >= 0) & (pix[:, 0] < cam.width) & (pix[:, 1] >= 0) & (pix[:, 1] < cam.height) & (z > 0)
        d = np.zeros(len(points))
        d[inside] = depth[pix[inside, 1], pix[inside, 0]]
        seen |= inside & (d > 0) & (np.abs(d - z) < VOXEL)
    return scene, depths, points, points[seen]


def test_gt_depth_fusion_reproduces_the_surface(spot):
    scene, depths, points, seen = spot
    mesh = tsdf_fusion(depths, scene.cameras, CFG, scene.radius, colors=scene.images, masks=scene.masks)
    assert isinstance(mesh, trimesh.Trimesh) and len(mesh.faces) > 1000
    to_gt = cKDTree(points).query(mesh.vertices)[0].mean()
    from_gt = cKDTree(mesh.vertices).query(seen)[0].mean()
    assert to_gt < VOXEL and from_gt < 1.5 * VOXEL, (to_gt, from_gt)
    assert mesh.visual.vertex_colors[:, :3].std() > 5  # colours were fused


def test_relative_parameters_are_scale_invariant(spot):
    scene, depths, _, _ = spot
    views = slice(0, 49, 4)
    cams, ds = scene.cameras[views], depths[views]
    base = tsdf_fusion(ds, cams, CFG, 1.0)
    for s in (1e-3, 1e3):  # the same scene in "millimetres" and "kilometres"
        scaled_cams = [replace(c, t=c.t * s) for c in cams]
        mesh = tsdf_fusion([d * s for d in ds], scaled_cams, CFG, scene_radius=s)
        assert abs(len(mesh.faces) - len(base.faces)) <= 0.01 * len(base.faces)
        d = cKDTree(base.vertices).query(mesh.vertices / s)[0]
        # open3d projects voxels in float32: at km scale (camera t ~ 3e3) a handful of voxels whose
        # projection lands on a pixel edge read the neighbouring pixel (5 of ~9 000 vertices move
        # by 0.6 voxel); every other vertex is where it is at scale 1
        assert np.mean(d < 0.05 * VOXEL) > 0.999 and d.max() < VOXEL, (s, np.sort(d)[-10:] / VOXEL)
    absolute = fusion_parameters(replace(CFG, absolute=True), scene_radius=1e3)
    assert absolute["voxel_size"] == VOXEL


def test_masks_and_alpha_remove_depth(spot):
    """One view, left half masked in: the mesh lies in the left half of that view (alpha likewise)."""
    scene, depths, _, _ = spot
    cam, depth = scene.cameras[0], depths[0]
    left = np.zeros(depth.shape, bool)
    left[:, : cam.width // 2] = True
    full = tsdf_fusion([depth], [cam], CFG, scene.radius)
    half = tsdf_fusion([depth], [cam], CFG, scene.radius, masks=[left])
    low_alpha = tsdf_fusion([depth], [cam], CFG, scene.radius, alphas=[np.where(left, 0.9, 0.1)])
    assert len(half.faces) < 0.8 * len(full.faces)
    assert len(low_alpha.faces) == len(half.faces)
    assert cam.project(full.vertices)[0][:, 0].max() > cam.width / 2 + 5
    assert cam.project(half.vertices)[0][:, 0].max() < cam.width / 2 + 1


def test_empty_and_mismatched_inputs_are_mesh_errors(spot):
    scene, depths, _, _ = spot
    cams, ds = scene.cameras[:3], depths[:3]
    with pytest.raises(MeshError, match="voxel_size=0.02.*alpha_threshold=0.5"):
        tsdf_fusion(ds, cams, CFG, 1.0, alphas=[np.zeros_like(d) for d in ds])
    with pytest.raises(MeshError, match="depth_trunc=0.5"):
        tsdf_fusion(ds, cams, replace(CFG, depth_trunc=0.5), 1.0)
    with pytest.raises(MeshError, match="2 depths for 3 cameras"):
        tsdf_fusion(ds[:2], cams, CFG, 1.0)
    with pytest.raises(MeshError, match="expected \\(72, 96\\)"):
        tsdf_fusion([d[:, :-1] for d in ds], cams, CFG, 1.0)
    with pytest.raises(MeshError, match="positive"):
        tsdf_fusion(ds, cams, replace(CFG, voxel_size=0.0), 1.0)
    nan_depths = [np.full_like(d, np.nan) for d in ds]
    with pytest.raises(MeshError, match="no depth"):
        tsdf_fusion(nan_depths, cams, CFG, 1.0)


def _o3d_spheres(counts):
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh()
    for i, resolution in enumerate(counts):
        sphere = o3d.geometry.TriangleMesh.create_sphere(radius=0.1, resolution=resolution)
        mesh += sphere.translate((i, 0.0, 0.0))
    return mesh


def test_keep_largest_clusters():
    sizes = [len(_o3d_spheres([r]).triangles) for r in (10, 6, 2)]
    assert sizes[2] < 50 < sizes[1] < sizes[0]
    assert len(keep_largest_clusters(_o3d_spheres([6, 10, 2]), 1).triangles) == sizes[0]
    assert len(keep_largest_clusters(_o3d_spheres([6, 10, 2]), 2).triangles) == sizes[0] + sizes[1]
    # the 50-triangle floor drops the small sphere even when 3 clusters are asked for
    kept = keep_largest_clusters(_o3d_spheres([6, 10, 2]), 3)
    assert len(kept.triangles) == sizes[0] + sizes[1]
    assert len(np.asarray(kept.vertices)) == len(np.unique(np.asarray(kept.triangles)))
    assert len(keep_largest_clusters(_o3d_spheres([6, 10, 2]), 0).triangles) == sum(sizes)


def test_canonical_order_depends_on_the_geometry_only():
    mesh = to_trimesh(_o3d_spheres([6, 10]).compute_vertex_normals())
    mesh.visual.vertex_colors = np.random.default_rng(0).integers(0, 256, (len(mesh.vertices), 4), np.uint8)
    rng = np.random.default_rng(1)
    perm = rng.permutation(len(mesh.vertices))  # the same mesh, vertices and faces listed in another order
    faces = np.argsort(perm)[mesh.faces][rng.permutation(len(mesh.faces))]
    faces = np.roll(faces, 1, axis=1)  # and each face starting at another corner (same orientation)
    shuffled = trimesh.Trimesh(mesh.vertices[perm], faces, vertex_colors=mesh.visual.vertex_colors[perm],
                               process=False)
    a, b = canonical_order(mesh), canonical_order(shuffled)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    assert np.array_equal(a.visual.vertex_colors, b.visual.vertex_colors)
    # nothing changed but the order: the same triangles, corners in the same cyclic order, same colours
    def triangles(m):
        corners = np.concatenate([m.vertices[m.faces], m.visual.vertex_colors[m.faces][..., :3]], -1)
        rank = np.lexsort(m.vertices[m.faces].reshape(-1, 3).T[::-1]).argsort().reshape(-1, 3)
        start = (rank.argmin(1)[:, None] + np.arange(3)) % 3  # each face from its smallest corner
        rows = np.take_along_axis(corners, start[..., None], 1).reshape(len(corners), -1)
        return rows[np.lexsort(rows.T[::-1])]

    assert np.array_equal(triangles(a), triangles(mesh))
    assert np.all(np.diff(a.vertices[:, 0]) >= 0)


@pytest.mark.parametrize("pixel", [(1, 1), (2, 3), (5, 7)])
def test_a_view_with_a_few_stray_pixels_is_skipped_not_a_crash(spot, pixel):
    """open3d allocates blocks from a subsampled pixel grid; a view whose only valid pixel falls
    between the samples (a thin plate seen edge-on) must add nothing instead of raising."""
    scene, depths, _, _ = spot
    stray = np.zeros_like(depths[0])
    stray[pixel[1], pixel[0]] = depths[0][depths[0] > 0].min()
    mesh = tsdf_fusion([depths[0], stray], scene.cameras[:2], CFG, scene.radius)
    alone = tsdf_fusion([depths[0]], scene.cameras[:1], CFG, scene.radius)
    assert len(mesh.faces) > 100 and abs(len(mesh.faces) - len(alone.faces)) <= 0.01 * len(alone.faces)


def _fused_plane_offset(slope: tuple[float, float]) -> float:
    """Mean signed distance (in voxels) of the TSDF mesh of a plane's exact depth to that plane.

    Plane z = 2 + a x + b y seen by a camera at the origin; depth sampled at pixel centres (i + 0.5);
    voxel = one pixel footprint at the plane's centre; vertices near the image border are ignored
    (the truncation band is cut off there).
    """
    from gsbench.data.camera import Camera

    width, height, f = 64, 48, 60.0
    cam = Camera(K=np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]]), R=np.eye(3),
                 t=np.zeros(3), width=width, height=height)
    normal = np.array([-slope[0], -slope[1], 1.0])  # n·X = 2
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rays = np.stack([(u - cam.cx) / f, (v - cam.cy) / f, np.ones_like(u)], axis=-1)
    depth = (2.0 / (rays @ normal)).astype(np.float32)  # camera z of each pixel ray's hit (ray z = 1)
    voxel = 2.0 / f
    cfg = MeshConfig(voxel_size=voxel, sdf_trunc=4 * voxel, depth_trunc=10.0, absolute=True, num_clusters=0)
    vertices = np.asarray(tsdf_fusion([depth], [cam], cfg).vertices)
    uv, _ = cam.project(vertices)
    inner = (uv[:, 0] > 6) & (uv[:, 0] < width - 6) & (uv[:, 1] > 6) & (uv[:, 1] < height - 6)
    assert inner.sum() > 200
    return float(((vertices[inner] @ normal - 2.0) / np.linalg.norm(normal)).mean() / voxel)


@pytest.mark.parametrize("axis", [0, 1])
def test_tilted_plane_fuses_without_pixel_shift(axis):
    """A half-pixel error in the intrinsic handed to open3d (the old ``cx - 0.5``) moves the fused
    plane by half a footprint times its slope, ±0.34 voxel at slope ±0.8 (sign with the slope); the
    TSDF's own discretisation bias is the same for both slopes (−0.02 to −0.06 voxel). So: the part
    that flips with the slope is under 0.05 voxel, and each offset under 0.1 voxel."""
    up, down = (_fused_plane_offset(tuple(s if k == axis else 0.0 for k in range(2))) for s in (0.8, -0.8))
    assert abs(up - down) / 2 < 0.05, (up, down)
    assert max(abs(up), abs(down)) < 0.1, (up, down)
