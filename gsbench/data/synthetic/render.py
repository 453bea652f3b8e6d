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
- Glass (``glass_ior`` set): the object (part 0) is a clear dielectric of that index in air
  (`gsbench.geometry.optics`), bending rays about its smooth normal (the outward vertex normals interpolated over
  the triangle, as the smooth surface the mesh samples would; a flat-faceted ball traps light by total
  internal reflection between facets, which a smooth one cannot). A ray that hits it splits into the mirror-reflected ray, weighted by the Fresnel
  reflectance R, and the refracted ray, weighted by 1 − R (none under total internal reflection); each
  goes on through the scene until it hits something opaque (shaded as above, times its weight), leaves
  into the black background, or has met the object `MAX_BOUNCES` times (then it adds nothing: black).
  Branches whose weight falls below `MIN_WEIGHT` are dropped. New rays start `OFFSET` (object units)
  off the interface on their own side. Mask, depth and normal stay those of the first hit: the glass
  surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from gsbench.data.camera import Camera
from gsbench.data.synthetic.primitives import Surface
from gsbench.errors import import_open3d
from gsbench.geometry.optics import fresnel, reflect, refract

LIGHT = np.array([0.35, -0.55, 0.76]) / np.linalg.norm([0.35, -0.55, 0.76])
MAX_BOUNCES = 16  # glass interactions a ray may have before it is dropped
MIN_WEIGHT = 1e-3  # a glass branch carrying less of the pixel than this is dropped
OFFSET = 1e-4  # object units: how far off the interface a reflected or refracted ray starts


@dataclass
class View:
    """One rendered view: rgb float32 HxWx3, mask bool HxW, depth float32 HxW, normal float32 HxWx3."""

    rgb: np.ndarray
    mask: np.ndarray
    depth: np.ndarray
    normal: np.ndarray


def _outward_vertex_normals(surface: Surface) -> np.ndarray:
    """Area-weighted vertex normals of ``surface`` (its triangles wound outward), unit; 0 where undefined."""
    v, t = surface.vertices, surface.triangles
    face = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])  # |face| = 2 x area
    normals = np.zeros_like(v, dtype=np.float64)
    for corner in range(3):
        np.add.at(normals, t[:, corner], face)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-30)


class Renderer:
    """Ray caster for one surface; cameras are in the surface's object frame."""

    def __init__(self, surface: Surface, *, specular: float = 0.0, shininess: float = 40.0,
                 ambient: float = 0.3, supersample: int = 2, glass_ior: float | None = None):
        o3d = import_open3d()
        self.surface, self.specular, self.shininess = surface, specular, shininess
        self.ambient, self.supersample, self.glass_ior = ambient, supersample, glass_ior
        self._vertex_normals = None if glass_ior is None else _outward_vertex_normals(surface)
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
        return dirs, self.cast(np.broadcast_to(camera.center, dirs.shape), dirs)

    @staticmethod
    def _facing_normals(dirs: np.ndarray, ans: dict) -> np.ndarray:
        """Geometric normals flipped to face the camera."""
        normals = ans["primitive_normals"].astype(np.float64)
        normals[np.sum(normals * dirs, axis=-1) > 0] *= -1.0
        return normals

    def _colour(self, points: np.ndarray, d: np.ndarray, normals: np.ndarray, ids: np.ndarray, uvs: np.ndarray) -> np.ndarray:
        """Shaded colour (N,3) of opaque hits at ``points`` seen along ``d`` (module docstring)."""
        albedo = self.surface.albedo(points, ids, uvs)
        ndotl = np.clip(normals @ LIGHT, 0.0, None)
        color = albedo * (self.ambient + (1.0 - self.ambient) * ndotl)[:, None]
        if self.specular > 0:
            half = LIGHT - d / np.linalg.norm(d, axis=1, keepdims=True)
            half /= np.linalg.norm(half, axis=1, keepdims=True)
            color += (self.specular * np.clip(np.sum(normals * half, axis=1), 0.0, None) ** self.shininess * (ndotl > 0))[:, None]
        if self.surface.unlit is not None:
            unlit = self.surface.unlit[ids]
            color[unlit] = albedo[unlit]
        return np.clip(color, 0.0, 1.0)

    def _is_object(self, ids: np.ndarray) -> np.ndarray:
        return np.ones(len(ids), bool) if self.surface.parts is None else self.surface.parts[ids] == 0

    def _shade(self, camera: Camera, dirs: np.ndarray, ans: dict) -> np.ndarray:
        hit = np.isfinite(ans["t_hit"])
        if self.glass_ior is not None:
            origins = np.broadcast_to(camera.center, dirs.shape).reshape(-1, 3)
            flat = {k: v.reshape(len(origins), *v.shape[dirs.ndim - 1:]) for k, v in ans.items()}
            return self._trace(origins, dirs.reshape(-1, 3), flat).reshape(dirs.shape)
        rgb = np.zeros(hit.shape + (3,))
        d, n = dirs[hit], self._facing_normals(dirs, ans)[hit]
        points = camera.center + ans["t_hit"][hit, None] * d
        rgb[hit] = self._colour(points, d, n, ans["primitive_ids"][hit].astype(np.int64),
                                ans["primitive_uvs"][hit].astype(np.float64))
        return rgb

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> dict:
        """open3d's answer for rays ``origins + t dirs`` (N,3 each)."""
        rays = np.concatenate([origins, dirs], axis=-1).astype(np.float32)
        return {k: v.numpy() for k, v in self.scene.cast_rays(self._o3d.core.Tensor(rays)).items()}

    def _trace(self, origins: np.ndarray, dirs: np.ndarray, ans: dict) -> np.ndarray:
        """Colour (N,3) of rays through a glass object (module docstring); ``ans`` is the rays' first cast."""
        colour = np.zeros((len(origins), 3))
        pixel, weight = np.arange(len(origins)), np.ones(len(origins))
        o, d = origins.astype(np.float64), dirs.astype(np.float64)
        for bounce in range(MAX_BOUNCES + 1):
            if bounce > 0:
                ans = self.cast(o, d)
            hit = np.isfinite(ans["t_hit"])
            ids = np.where(hit, ans["primitive_ids"], 0).astype(np.int64)
            glass = hit & self._is_object(ids)
            opaque = hit & ~glass
            if opaque.any():
                p = o[opaque] + ans["t_hit"][opaque, None] * d[opaque]
                facing = self._facing_normals(d[opaque], {"primitive_normals": ans["primitive_normals"][opaque]})
                c = self._colour(p, d[opaque], facing, ids[opaque], ans["primitive_uvs"][opaque].astype(np.float64))
                np.add.at(colour, pixel[opaque], weight[opaque, None] * c)
            if bounce == MAX_BOUNCES or not glass.any():
                break
            o, d, pixel, weight = self._split(o[glass], d[glass], ans["t_hit"][glass], ans["primitive_normals"][glass],
                                              self._smooth_normals(ids[glass], ans["primitive_uvs"][glass]),
                                              pixel[glass], weight[glass])
        return colour

    def _smooth_normals(self, ids: np.ndarray, uvs: np.ndarray) -> np.ndarray:
        """The glass's shading normals at hits: its outward vertex normals interpolated with open3d's
        barycentric (u, v) (point = (1 − u − v) v₀ + u v₁ + v v₂), unit."""
        corners = self._vertex_normals[self.surface.triangles[ids]]
        u, v = uvs[:, :1].astype(np.float64), uvs[:, 1:2].astype(np.float64)
        n = (1.0 - u - v) * corners[:, 0] + u * corners[:, 1] + v * corners[:, 2]
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)

    def _split(self, o, d, t_hit, outward, smooth, pixel, weight):
        """The reflected and refracted rays (origins, unit directions, pixels, weights) of rays meeting the
        glass at ``o + t_hit d``; ``outward`` the triangles' outward normals, which say whether a ray enters
        or leaves, ``smooth`` the shading normals it bends about (the triangle's where the two disagree on
        the side, near a silhouette); weights < `MIN_WEIGHT` dropped."""
        p = o + t_hit[:, None] * d
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        outward = outward.astype(np.float64)
        outward /= np.linalg.norm(outward, axis=1, keepdims=True)
        side = np.sum(d * outward, axis=1)
        entering = side < 0
        agree = np.sign(np.sum(d * smooth, axis=1)) == np.sign(side)
        outward = np.where(agree[:, None], smooth, outward)
        n = np.where(entering[:, None], outward, -outward)
        n1, n2 = np.where(entering, 1.0, self.glass_ior), np.where(entering, self.glass_ior, 1.0)
        d_t, n_t = torch.from_numpy(d), torch.from_numpy(n)
        r = fresnel(-(d_t * n_t).sum(-1), torch.from_numpy(n1), torch.from_numpy(n2)).numpy()
        through, tir = (x.numpy() for x in refract(d_t, n_t, torch.from_numpy(n1 / n2)))
        go = ~tir
        origins = np.concatenate([p + OFFSET * n, p[go] - OFFSET * n[go]])
        directions = np.concatenate([reflect(d_t, n_t).numpy(), through[go]])
        weights = np.concatenate([weight * r, weight[go] * (1.0 - r[go])])
        pixels = np.concatenate([pixel, pixel[go]])
        keep = weights >= MIN_WEIGHT
        return origins[keep], directions[keep], pixels[keep], weights[keep]

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
