"""The visual hull of a scene's object masks: which 3D points every view's mask allows.

A point ``X`` is inside the hull when at least ``min_views`` cameras see it (in front of the camera,
``z > 0``, projected into the image) and every camera that sees it has it inside the mask:

    inside(X) = |S(X)| >= min_views  and  ∀ c ∈ S(X): mask_c[floor(v_c), floor(u_c)],
    S(X) = {c : z_c(X) > 0, 0 <= u_c(X) < W_c, 0 <= v_c(X) < H_c},  (u_c, v_c) = π_c(X)

(pixel (i, j) covers [i, i+1) x [j, j+1) with its centre at i + 0.5, `gsbench.data.camera`). A view
that does not see ``X`` does not carve it: the hull of a partial capture is the intersection of the
viewing cones of the views that see each point. ``dilate_px`` grows every mask by that many pixels
first (``scipy.ndimage.binary_dilation``), so a surface on the silhouette is not carved by the
pixel discretisation of a mask.

Used for the initial points of scenes with masks and no SfM points (`methods.base`) and for the
share of a mesh outside the hull (floaters).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import binary_dilation

from gsbench.data.camera import Camera
from gsbench.errors import DataError


def _dilated(mask: np.ndarray, pixels: int) -> np.ndarray:
    if pixels <= 0:
        return mask
    return binary_dilation(mask, iterations=int(pixels))


def inside_visual_hull(points: np.ndarray, cameras: list[Camera], masks: list[np.ndarray], *,
                       dilate_px: int = 0, min_views: int = 1) -> np.ndarray:
    """Boolean (N,) of which ``points`` (N,3, the cameras' frame) are inside the hull (module docstring)."""
    if len(cameras) != len(masks):
        raise DataError(f"visual hull: {len(cameras)} cameras but {len(masks)} masks; fix: one mask per camera")
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    seen = np.zeros(len(points), dtype=np.int64)
    inside = np.ones(len(points), dtype=bool)
    for cam, mask in zip(cameras, masks):
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != (cam.height, cam.width):
            raise DataError(f"visual hull: mask of view '{cam.name}' is {mask.shape[1]}x{mask.shape[0]} but its "
                            f"camera is {cam.width}x{cam.height}; fix: load masks at the cameras' resolution")
        mask = _dilated(mask, dilate_px)
        uv, z = cam.project(points)
        with np.errstate(invalid="ignore"):
            col, row = np.floor(uv[:, 0]), np.floor(uv[:, 1])
            visible = (z > 0) & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        idx = np.flatnonzero(visible)
        seen[idx] += 1
        inside[idx] &= mask[row[idx].astype(np.int64), col[idx].astype(np.int64)]
    return inside & (seen >= min_views)
