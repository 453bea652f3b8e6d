"""GOF tetrahedra mesh extraction (gsbench.mesh.tets, docs/methods/gof.md §7)."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import Delaunay, cKDTree
from scipy.spatial.transform import Rotation

from gsbench.mesh import MeshError
from gsbench.mesh.tets import (
    BOX_CORNERS,
    frustum_mask,
    marching_tetrahedra,
    point_budget,
    tetra_mesh,
    tetra_points,
)
from gsbench.raster import RasterGaussians, RasterSettings, integrate
from tests.raster_scenes import look_at_camera, make_camera, random_gaussians

RADIUS = 1.0
SPACING = 0.15


def sphere_sdf(p: np.ndarray) -> np.ndarray:
    return np.linalg.norm(p, axis=1) - RADIUS


@pytest.fixture(scope="module")
def jittered_grid():
    """A jittered grid on [-1.5, 1.5]³ (spacing 0.15) and its Delaunay tets."""
    rng = np.random.default_rng(0)
    ax = np.arange(-1.5, 1.5 + 1e-9, SPACING)
    grid = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    points = grid + rng.uniform(-0.3 * SPACING, 0.3 * SPACING, grid.shape)
    return points, Delaunay(points).simplices


def test_sphere_is_watertight_outward_and_close(jittered_grid):
    points, tets = jittered_grid
    v, f = marching_tetrahedra(points, tets, sphere_sdf(points), sphere_sdf, level=0.0, bisection_steps=8)
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0.95 * 4 / 3 * np.pi * RADIUS**3  # positive: normals point outwards (sdf > 0)
    assert np.abs(sphere_sdf(v)).max() < 1e-3 * RADIUS  # vertices on the sphere (bisection precision)
    surface = mesh.sample(5000, seed=0)
    assert np.abs(sphere_sdf(surface)).mean() < 0.01 * RADIUS  # chords stay close to the sphere
    sphere = np.random.default_rng(1).normal(size=(5000, 3))
    sphere *= RADIUS / np.linalg.norm(sphere, axis=1, keepdims=True)
    assert cKDTree(v).query(sphere)[0].max() < SPACING  # and cover it


def test_linear_interpolation_without_field_fn(jittered_grid):
    points, tets = jittered_grid
    v, f = marching_tetrahedra(points, tets, sphere_sdf(points), None, level=0.0)
    assert len(f) > 1000 and np.abs(sphere_sdf(v)).mean() < 0.01 * RADIUS
    with pytest.raises(ValueError, match="field_fn"):
        marching_tetrahedra(points, tets, sphere_sdf(points), None, bisection_steps=2)


def test_level_and_sign_convention(jittered_grid):
    """``level`` selects the iso-value; the faces point to the ``values > level`` side."""
    points, tets = jittered_grid
    r = np.linalg.norm(points, axis=1)
    v, f = marching_tetrahedra(points, tets, -r, lambda p: -np.linalg.norm(p, axis=1), level=-0.8, bisection_steps=8)
    assert np.abs(np.linalg.norm(v, axis=1) - 0.8).max() < 1e-3
    assert trimesh.Trimesh(v, f, process=False).volume < 0  # above = inside: normals point inwards


def test_bisection_is_monotone(jittered_grid):
    points, tets = jittered_grid
    errors = []
    for steps in (0, 2, 4, 8):
        v, _ = marching_tetrahedra(points, tets, sphere_sdf(points), sphere_sdf, level=0.0, bisection_steps=steps)
        errors.append(np.abs(sphere_sdf(v)))
    for coarse, fine in zip(errors, errors[1:]):
        assert fine.mean() <= coarse.mean() and fine.max() <= coarse.max()
    assert errors[-1].mean() < errors[0].mean() / 50


def test_tetra_points_are_centre_then_3_sigma_box_corners():
    g = random_gaussians(5, "raymax", seed=3, filter3d=0.01)
    g.quats = 2.0 * g.quats  # not normalised: normalised as the rasterizer does
    pts = tetra_points(g).numpy()
    assert pts.shape == (5, 9, 3)
    np.testing.assert_allclose(pts[:, 0], g.means.numpy())
    q = g.quats.numpy()
    rot = Rotation.from_quat(np.concatenate([q[:, 1:], q[:, :1]], 1)).as_matrix()  # scipy: (x, y, z, w)
    s_eff = np.sqrt(g.scales.numpy() ** 2 + 0.01)
    expected = g.means.numpy()[:, None] + np.einsum("nij,nkj->nki", rot, 3.0 * s_eff[:, None] * BOX_CORNERS)
    np.testing.assert_allclose(pts[:, 1:], expected, atol=1e-12)
    local = np.einsum("nji,nkj->nki", rot, pts[:, 1:] - pts[:, :1])  # back in the Gaussian frame
    np.testing.assert_allclose(np.abs(local), np.broadcast_to(3.0 * s_eff[:, None], local.shape), atol=1e-12)


def test_frustum_mask_drops_points_behind_and_outside():
    front = make_camera(16, 16)  # at the origin, looking down +z
    pts = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, -2.0], [0.0, 0.0, 0.1], [5.0, 0.0, 2.0], [0.0, 0.0, 200.0]])
    np.testing.assert_array_equal(frustum_mask(pts, [front], near=0.2, far=100.0), [1, 0, 0, 0, 0])
    back = look_at_camera((0.0, 0.0, 0.0), (0.0, 0.0, -1.0))
    np.testing.assert_array_equal(frustum_mask(pts, [front, back], near=0.2, far=100.0), [1, 1, 0, 0, 0])


def sphere_of_splats(n: int = 300, radius: float = 0.5, opacity: float = 0.9) -> RasterGaussians:
    """Flat Gaussians (0.06, 0.06, 0.01) tangent to a sphere, on a Fibonacci lattice."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (1.0 + 5**0.5) * k
    normals = np.stack([np.sqrt(1 - z**2) * np.cos(phi), np.sqrt(1 - z**2) * np.sin(phi), z], 1)
    axis = np.cross([0.0, 0.0, 1.0], normals)
    angle = np.arccos(np.clip(normals[:, 2], -1.0, 1.0))
    rotvec = axis / np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-12) * angle[:, None]
    xyzw = Rotation.from_rotvec(rotvec).as_quat()  # local z -> normal
    f32 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    return RasterGaussians(
        means=f32(radius * normals),
        quats=f32(np.concatenate([xyzw[:, 3:], xyzw[:, :3]], 1)),
        scales=f32(np.tile([0.06, 0.06, 0.01], (n, 1))),
        opacities=f32(np.full(n, opacity)),
        sh=torch.zeros(n, 1, 3),
    )


@pytest.fixture(scope="module")
def ring_of_cameras():
    eyes = [(2.5, 0.3, 0.2), (-2.5, -0.2, 0.3), (0.2, 2.5, -0.3), (-0.3, -2.5, 0.2), (0.3, 0.2, 2.5), (-0.2, 0.3, -2.5)]
    return [look_at_camera(e, (0.0, 0.0, 0.0), 48, 48, fov_x_deg=40.0) for e in eyes]


def test_tetra_mesh_of_a_sphere_of_splats(ring_of_cameras):
    mesh = tetra_mesh(sphere_of_splats(), ring_of_cameras, RasterSettings())
    assert isinstance(mesh, trimesh.Trimesh) and len(mesh.faces) > 500
    assert np.isfinite(mesh.vertices).all() and mesh.is_watertight
    r = np.linalg.norm(mesh.vertices, axis=1)  # the 0.5 level lies just outside the splats (σ_normal = 0.01)
    assert r.min() > 0.5 and r.max() < 0.55, (r.min(), r.max())
    outward = np.einsum("ij,ij->i", mesh.face_normals, mesh.triangles_center)
    assert (outward > 0).all()  # normals point to free space


def test_tetra_mesh_equals_marching_on_the_exact_field(ring_of_cameras):
    """The sign queries (early exits, view hints) give exactly the mesh of the exact-value field."""
    g, settings = sphere_of_splats(), RasterSettings()
    mesh = tetra_mesh(g, ring_of_cameras, settings, bisection_steps=4)
    grid = tetra_points(g).to(torch.float64).numpy().reshape(-1, 3)
    points = grid[frustum_mask(grid, ring_of_cameras, settings.near, settings.far)]

    def sdf(x):
        exact = integrate(g, ring_of_cameras, torch.as_tensor(x, dtype=torch.float64), settings=settings)
        return 0.5 - exact.to(torch.float64).numpy()

    v, f = marching_tetrahedra(points, Delaunay(points).simplices, sdf(points), sdf, level=0.0, bisection_steps=4)
    np.testing.assert_array_equal(mesh.vertices, v)
    np.testing.assert_array_equal(mesh.faces, f)


def test_point_budget_keeps_whole_gaussians_by_priority():
    seen = np.ones((4, 9), dtype=bool)
    seen[3, :4] = False  # 5 points
    kept = point_budget(seen, np.array([0.1, 0.9, 0.5, 0.7]), max_points=16)
    np.testing.assert_array_equal(kept.any(1), [False, True, False, True])
    np.testing.assert_array_equal(kept[3], seen[3])
    assert point_budget(seen, np.zeros(4), max_points=32) is seen


def test_tetra_mesh_warns_when_over_budget(ring_of_cameras, caplog):
    g = sphere_of_splats()
    g.opacities[::2] = 0.3  # the budget keeps the 0.9 ones
    with caplog.at_level(logging.WARNING, logger="gsbench.mesh.tets"):
        mesh = tetra_mesh(g, ring_of_cameras, RasterSettings(), max_points=9 * 150, bisection_steps=2)
    assert "max_points=1350" in caplog.text and "keeping the 150 of 300 Gaussians" in caplog.text
    assert len(mesh.faces) > 0


def test_transparent_gaussians_raise_mesh_error(ring_of_cameras):
    with pytest.raises(MeshError, match="level=0.5.*bisection_steps=8"):
        tetra_mesh(sphere_of_splats(opacity=1e-3), ring_of_cameras, RasterSettings())
