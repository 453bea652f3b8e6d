"""Random scene builders shared by the rasterizer tests (fast path and dense reference).

All builders are deterministic given ``seed`` and return leaf tensors (``requires_grad=False``;
call `with_grad` to get a copy whose parameters require grad).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from gsbench.data.camera import Camera
from gsbench.raster.types import RasterGaussians


def make_camera(
    width: int = 16,
    height: int = 16,
    *,
    fov_x_deg: float = 60.0,
    fy: float | None = None,
    cx: float | None = None,
    cy: float | None = None,
    R: np.ndarray | None = None,
    t: np.ndarray | None = None,
    name: str = "test",
) -> Camera:
    """A pinhole camera; default identity pose (camera at the origin looking down +z), centred principal point."""
    fx = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2.0)
    K = np.array(
        [[fx, 0.0, width / 2.0 if cx is None else cx], [0.0, fx if fy is None else fy, height / 2.0 if cy is None else cy], [0.0, 0.0, 1.0]]
    )
    return Camera(
        K=K,
        R=np.eye(3) if R is None else np.asarray(R, dtype=np.float64),
        t=np.zeros(3) if t is None else np.asarray(t, dtype=np.float64),
        width=width,
        height=height,
        name=name,
    )


def look_at_camera(eye, target, width: int = 16, height: int = 16, fov_x_deg: float = 60.0, up=(0.0, -1.0, 0.0)) -> Camera:
    """An OpenCV camera at ``eye`` looking at ``target`` (y down in the image)."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(np.asarray(up, dtype=np.float64), z)
    if np.linalg.norm(x) < 1e-8:
        x = np.cross(np.array([1.0, 0.0, 0.0]), z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in world
    return make_camera(width, height, fov_x_deg=fov_x_deg, R=R, t=-R @ eye)


def random_quats(n: int, gen: torch.Generator, dtype=torch.float64) -> torch.Tensor:
    """Uniformly random unit quaternions (w, x, y, z)."""
    q = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    return (q / q.norm(dim=-1, keepdim=True)).to(dtype)


def random_gaussians(
    n: int,
    kernel: str = "ewa",
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
    *,
    camera: Camera | None = None,
    depth_range: tuple[float, float] = (2.0, 4.0),
    scale_range: tuple[float, float] = (0.05, 0.3),
    opacity_range: tuple[float, float] = (0.3, 0.9),
    sh_degree: int = 0,
    spread: float = 0.8,
    filter3d: float | None = None,
) -> RasterGaussians:
    """``n`` Gaussians in front of ``camera`` (default: `make_camera()` at the origin).

    Centres: camera depth uniform in ``depth_range``, image position uniform within ``spread`` of the
    half field of view (so they project inside the image); then mapped to world with the camera pose.
    Scales log-uniform in ``scale_range`` (2 columns for ``surfel``, 3 otherwise); SH coefficients
    ~ N(0, 0.3²) with K = (sh_degree+1)² bands; ``filter3d`` a constant variance if given.
    """
    cam = camera if camera is not None else make_camera()
    gen = torch.Generator().manual_seed(seed)
    u = lambda *shape: torch.rand(*shape, generator=gen, dtype=torch.float64)  # noqa: E731
    z = depth_range[0] + (depth_range[1] - depth_range[0]) * u(n)
    half_x = 0.5 * cam.width / cam.fx
    half_y = 0.5 * cam.height / cam.fy
    ndc = (2.0 * u(n, 2) - 1.0) * spread
    x_over_z = (0.5 * cam.width - cam.cx) / cam.fx + ndc[:, 0] * half_x  # pixel u = W/2 + ndc·spread·W/2
    y_over_z = (0.5 * cam.height - cam.cy) / cam.fy + ndc[:, 1] * half_y
    pc = torch.stack([x_over_z * z, y_over_z * z, z], dim=-1)
    R = torch.as_tensor(cam.R, dtype=torch.float64)
    t = torch.as_tensor(cam.t, dtype=torch.float64)
    means = (pc - t) @ R  # x_w = Rᵀ (x_c − t)
    ncols = 2 if kernel == "surfel" else 3
    lo, hi = math.log(scale_range[0]), math.log(scale_range[1])
    scales = torch.exp(lo + (hi - lo) * u(n, ncols))
    opac = opacity_range[0] + (opacity_range[1] - opacity_range[0]) * u(n)
    K = (sh_degree + 1) ** 2
    sh = 0.3 * torch.randn(n, K, 3, generator=gen, dtype=torch.float64)
    f3d = None if filter3d is None else torch.full((n,), float(filter3d), dtype=dtype)
    return RasterGaussians(
        means=means.to(dtype),
        quats=random_quats(n, gen, dtype),
        scales=scales.to(dtype),
        opacities=opac.to(dtype),
        sh=sh.to(dtype),
        filter3d=f3d,
    )


def single_gaussian(
    mean_cam,
    *,
    kernel: str = "ewa",
    quat=(1.0, 0.0, 0.0, 0.0),
    scales=(0.1, 0.1, 0.1),
    opacity: float = 0.5,
    rgb=(0.5, 0.5, 0.5),
    dtype: torch.dtype = torch.float64,
) -> RasterGaussians:
    """One Gaussian at ``mean_cam`` (world = camera frame for the identity `make_camera`), constant colour ``rgb``.

    The DC SH coefficient is ``(rgb − 0.5)/C0`` so that the degree-0 SH colour equals ``rgb``.
    """
    c0 = 0.28209479177387814
    ncols = 2 if kernel == "surfel" else 3
    sh = ((torch.tensor(rgb, dtype=torch.float64) - 0.5) / c0).reshape(1, 1, 3)
    return RasterGaussians(
        means=torch.tensor([mean_cam], dtype=dtype),
        quats=torch.tensor([quat], dtype=dtype),
        scales=torch.tensor([list(scales)[:ncols]], dtype=dtype),
        opacities=torch.tensor([opacity], dtype=dtype),
        sh=sh.to(dtype),
    )


def with_grad(g: RasterGaussians) -> RasterGaussians:
    """A copy of ``g`` whose means, quats, scales, opacities and sh are fresh leaves requiring grad."""
    leaf = lambda x: x.detach().clone().requires_grad_(True)  # noqa: E731
    return RasterGaussians(
        means=leaf(g.means),
        quats=leaf(g.quats),
        scales=leaf(g.scales),
        opacities=leaf(g.opacities),
        sh=leaf(g.sh),
        filter3d=None if g.filter3d is None else g.filter3d.detach().clone(),
    )


def concat(*gs: RasterGaussians) -> RasterGaussians:
    """Concatenate several Gaussian sets (same SH size); filter3d kept only if all have it."""
    f = [g.filter3d for g in gs]
    return RasterGaussians(
        means=torch.cat([g.means for g in gs]),
        quats=torch.cat([g.quats for g in gs]),
        scales=torch.cat([g.scales for g in gs]),
        opacities=torch.cat([g.opacities for g in gs]),
        sh=torch.cat([g.sh for g in gs]),
        filter3d=None if any(x is None for x in f) else torch.cat(f),
    )
