"""Depth maps and the pixel rays they are measured along.

Every module that needs the pixel grid takes it from here: pixel (i, j) is centred at (i + 0.5, j + 0.5)
(`gsbench.data.camera`), its camera-space ray is ((i + 0.5 − cx)/fx, (j + 0.5 − cy)/fy, 1), so a camera-z
depth d puts the pixel's point at d · ray.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from gsbench.data.camera import Camera


def pixel_centres(camera: Camera, dtype=torch.float64) -> torch.Tensor:
    """(H,W,2) pixel-centre coordinates (i + 0.5, j + 0.5), row-major (row j, column i)."""
    j, i = torch.meshgrid(torch.arange(camera.height, dtype=torch.float64),
                          torch.arange(camera.width, dtype=torch.float64), indexing="ij")
    return torch.stack([i + 0.5, j + 0.5], -1).to(dtype)


def pixel_rays(camera: Camera, dtype=torch.float32) -> torch.Tensor:
    """(H,W,3) camera-space rays ((i+0.5−cx)/fx, (j+0.5−cy)/fy, 1) of the pixel centres, computed in float64."""
    centres = pixel_centres(camera)
    x = (centres[..., 0] - camera.cx) / camera.fx
    y = (centres[..., 1] - camera.cy) / camera.fy
    return torch.stack([x, y, torch.ones_like(x)], -1).to(dtype)


def world_rays(camera: Camera, pixels: np.ndarray | None = None) -> np.ndarray:
    """(H·W, 6) rays (origin, direction) through every pixel centre in the camera's world frame, row-major
    (row j, then column i), or only through the row-major pixel indices ``pixels`` (N,); direction
    Rᵀ K⁻¹ (i + 0.5, j + 0.5, 1), not normalised."""
    if pixels is None:
        centres = pixel_centres(camera).reshape(-1, 2).numpy()
    else:
        centres = np.column_stack([pixels % camera.width + 0.5, pixels // camera.width + 0.5]).astype(np.float64)
    pix = np.column_stack([centres, np.ones(len(centres))])
    dirs = (pix @ np.linalg.inv(np.asarray(camera.K, np.float64)).T) @ np.asarray(camera.R, np.float64)
    return np.concatenate([np.broadcast_to(camera.center, dirs.shape), dirs], axis=1)


def depth_to_normal(depth: torch.Tensor, camera: Camera) -> torch.Tensor:
    """Unit camera-space normals (H,W,3) from a camera-z depth map (2DGS ``depth_to_normal``, docs/methods/2dgs.md §4.3).

    X = depth · ray; dx = X[r+1,c] − X[r−1,c], dy = X[r,c+1] − X[r,c−1] (central differences);
    n = normalize(dx × dy), which faces the camera (y down); the 1-pixel border is 0. Camera space
    rather than world space: the consistency dot product is rotation invariant. Rays use the
    camera's pixel-centre convention (cx = W/2 is the centre), not 2DGS's half-pixel-shifted
    integer pixels (docs/methods/2dgs.md §4.3, §8).
    """
    points = depth[..., None] * pixel_rays(camera, depth.dtype)
    dx = points[2:, 1:-1] - points[:-2, 1:-1]
    dy = points[1:-1, 2:] - points[1:-1, :-2]
    n = F.normalize(torch.cross(dx, dy, dim=-1), dim=-1)
    return F.pad(n.permute(2, 0, 1), (1, 1, 1, 1)).permute(1, 2, 0)
