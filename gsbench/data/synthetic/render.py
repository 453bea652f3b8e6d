"""CPU ray casting of a `Surface` (open3d ``RaycastingScene``) into RGB, mask, depth and normal maps.

Per pixel (i, j) the ray goes through ``(i + 0.5, j + 0.5)`` (gsbench convention) with camera-space
direction ``K⁻¹ (u, v, 1)``, whose z is 1, so the hit parameter is the camera z (depth).
- mask, depth (camera z, 0 outside) and normal (camera space, unit, facing the camera, 0 outside)
  come from the pixel-centre ray; for a multi-part surface (an object in its environment,
  ``environment.py``) depth and normal are those of the first hit of any part and the mask is
  "the first hit is the object" (part 0), like a DTU object mask; the normal is the triangle's geometric normal, i.e. the exact
  normal of the mesh the GT points are sampled from.
- RGB averages ``supersample`` x ``supersample`` rays per pixel (box-filtered anti-aliasing; the
  background is black). Shading: ``albedo * (ambient + (1 - ambient) max(0, n·l))`` with a fixed
  light direction ``l`` in the object frame, plus, when ``specular`` > 0, a white Blinn-Phong term
  ``specular * max(0, n·h)^shininess`` (view dependent). Triangles marked ``unlit`` (a sky) show
  their albedo unshaded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gsbench.data.camera import Camera
from gsbench.data.synthetic.primitives import Surface
from gsbench.errors import import_open3d

LIGHT = np.array([0.35, -0.55, 0.76]) / np.linalg.norm([0.35, -0.55, 0.76])


@dataclass
class View:
    """One rendered view: rgb float32 HxWx3, mask bool HxW, depth float32 HxW, normal float32 HxWx3."""

    rgb: np.ndarray
    mask: np.ndarray
    depth: np.ndarray
    normal: np.ndarray


class Renderer:
    """Ray caster for one surface; cameras are in the surface's object frame."""

    def __init__(self, surface: Surface, *, specular: float = 0.0, shininess: float = 40.0,
                 ambient: float = 0.3, supersample: int = 2):
        o3d = import_open3d()
        self.surface, self.specular, self.shininess = surface, specular, shininess
        self.ambient, self.supersample = ambient, supersample
        self.scene = o3d.t.geometry.RaycastingScene()
        mesh = o3d.t.geometry.TriangleMesh()
        mesh.vertex.positions = o3d.core.Tensor(surface.vertices.astype(np.float32))
        mesh.triangle.indices = o3d.core.Tensor(surface.triangles.astype(np.int32))
        self.scene.add_triangles(mesh)
        self._o3d = o3d

    def _cast(self, camera: Camera, dx: float, dy: float):
        """Rays through ``(i + dx, j + dy)``; returns world directions (H,W,3) and the open3d answer."""
        jj, ii = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
        pix = np.stack([ii + dx, jj + dy, np.ones_like(ii)], axis=-1)
        dirs = np.einsum("ij,hwj->hwi", camera.R.T @ np.linalg.inv(camera.K), pix)  # world direction Rᵀ K⁻¹ (u, v, 1)
        rays = np.concatenate([np.broadcast_to(camera.center, dirs.shape), dirs], axis=-1).astype(np.float32)
        ans = self.scene.cast_rays(self._o3d.core.Tensor(rays))
        return dirs, {k: v.numpy() for k, v in ans.items()}

    @staticmethod
    def _facing_normals(dirs: np.ndarray, ans: dict) -> np.ndarray:
        """Geometric normals flipped to face the camera."""
        normals = ans["primitive_normals"].astype(np.float64)
        normals[np.sum(normals * dirs, axis=-1) > 0] *= -1.0
        return normals

    def _shade(self, camera: Camera, dirs: np.ndarray, ans: dict) -> np.ndarray:
        hit = np.isfinite(ans["t_hit"])
        rgb = np.zeros(hit.shape + (3,))
        d, n = dirs[hit], self._facing_normals(dirs, ans)[hit]
        points = camera.center + ans["t_hit"][hit, None] * d
        albedo = self.surface.albedo(points, ans["primitive_ids"][hit].astype(np.int64), ans["primitive_uvs"][hit].astype(np.float64))
        ndotl = np.clip(n @ LIGHT, 0.0, None)
        color = albedo * (self.ambient + (1.0 - self.ambient) * ndotl)[:, None]
        if self.specular > 0:
            half = LIGHT - d / np.linalg.norm(d, axis=1, keepdims=True)
            half /= np.linalg.norm(half, axis=1, keepdims=True)
            color += (self.specular * np.clip(np.sum(n * half, axis=1), 0.0, None) ** self.shininess * (ndotl > 0))[:, None]
        if self.surface.unlit is not None:
            unlit = self.surface.unlit[ans["primitive_ids"][hit].astype(np.int64)]
            color[unlit] = albedo[unlit]
        rgb[hit] = np.clip(color, 0.0, 1.0)
        return rgb

    def depth(self, camera: Camera) -> np.ndarray:
        """Camera-z depth of the pixel-centre rays (0 where nothing is hit): `render`'s depth alone."""
        _, ans = self._cast(camera, 0.5, 0.5)
        return np.where(np.isfinite(ans["t_hit"]), ans["t_hit"], 0.0).astype(np.float32)

    def render(self, camera: Camera) -> View:
        """Render one view (see the module docstring)."""
        dirs, ans = self._cast(camera, 0.5, 0.5)
        hit = np.isfinite(ans["t_hit"])
        mask = hit
        if self.surface.parts is not None:
            mask = hit & (self.surface.parts[np.where(hit, ans["primitive_ids"], 0).astype(np.int64)] == 0)
        offsets = (np.arange(self.supersample) + 0.5) / self.supersample
        rgb = sum(self._shade(camera, *self._cast(camera, dx, dy)) for dx in offsets for dy in offsets)
        depth = np.where(hit, ans["t_hit"], 0.0).astype(np.float32)
        normal_cam = np.where(hit[..., None], np.einsum("ij,hwj->hwi", camera.R, self._facing_normals(dirs, ans)), 0.0).astype(np.float32)
        return View(rgb=(rgb / self.supersample**2).astype(np.float32), mask=mask, depth=depth, normal=normal_cam)
