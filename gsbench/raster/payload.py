"""What a projection produces, and the camera and rotation helpers both projections share
(`gsbench.raster.projection_fused`, `gsbench.raster.projection_torch`; `gsbench.raster.projection` chooses).

A `Projection` holds
the per-Gaussian *payload* (one (N, P) tensor the C++ compositor reads, column layout below), the
screen radius, visibility, centre depth (the per-tile sort key), the tile rectangle and a conservative
pixel box outside which the Gaussian's alpha is certainly < 1/255 (used to skip rows and tiles; it never
changes a result).

Column layout of the payload (must match ``csrc/composite.cpp``):

    common   0 mx  1 my  2-4 conic (A, B, C)  5 opacity  6-8 rgb
    ewa      9 z        10-12 normal
    rade     9 l        10-11 p/f (pixel units)  12-14 normal
    raymax   9-14 A' = Σ⁻¹/c (00,01,02,11,12,22)  15-17 b' = Σ⁻¹μ/c  18-20 M' (00,01,11)  21 c  22-23 μxy/μz
    surfel   9-11 n (camera-facing normal)  12 d = n·μ  13-15 a_u = t_u/s_u  16 μ·a_u  17-19 a_v  20 μ·a_v

Raymax is evaluated without cancellation: with Δ = r − μ/μz (Δz = 0) the Mahalanobis distance from μ to
the ray r is ``q = c − (b·r)²/(rᵀAr) = ΔᵀMΔ/(rᵀAr)``, M = (c A − b bᵀ)_xy = Gram matrix of
``μ̃ × ẽ_x, μ̃ × ẽ_y`` in whitened coordinates; A, b, M are stored divided by c (resp. c²) so that
neither tiny nor huge scales overflow float32. Mathematically identical to the contract's A, b, c.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from gsbench.data.camera import Camera

NUM_PARAMS = {"ewa": 13, "rade": 15, "raymax": 24, "surfel": 21}


@dataclass
class Projection:
    params: torch.Tensor  # (N, P) differentiable payload
    means2d: torch.Tensor  # (N, 2) pixels, detached, 0 where culled (the differentiable copy is params[:, :2])
    radii: torch.Tensor  # (N,) int64
    visible: torch.Tensor  # (N,) bool
    depth: torch.Tensor  # (N,) centre camera z, detached (sort key)
    bounds: torch.Tensor  # (N, 4) xmin, xmax, ymin, ymax pixel box of alpha >= 1/255 (detached)
    rect: torch.Tensor  # (N, 4) int32 tile rectangle x0, x1, y0, y1 (exclusive ends), refined by `bounds`
    rect_radius: torch.Tensor  # (N, 4) int32 tile rectangle of the 3σ radius only (integrate)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """(N,4) unit quaternions (w,x,y,z) -> (N,3,3) rotation matrices."""
    w, x, y, z = q.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return torch.stack(
        [
            1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
            2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
            2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)


def camera_tensors(camera: Camera, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    R = torch.as_tensor(camera.R, dtype=dtype)
    t = torch.as_tensor(camera.t, dtype=dtype).reshape(3)
    center = torch.as_tensor(camera.center, dtype=dtype).reshape(3)
    return R, t, center


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a proper rotation matrix (Shepperd's method)."""
    m = np.asarray(R, dtype=np.float64)
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def left_mult(camera: Camera, dtype: torch.dtype) -> torch.Tensor:
    """4×4 matrix L with q_cw ⊗ q = L q (Hamilton product), q_cw the quaternion of the camera rotation."""
    R = np.asarray(camera.R, dtype=np.float64)
    if np.linalg.det(R) < 0:
        raise ValueError("camera.R must be a proper rotation (det +1)")
    w, x, y, z = rotmat_to_quat(R)
    L = np.array([[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]])
    return torch.as_tensor(L, dtype=dtype)
