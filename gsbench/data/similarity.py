"""Similarity transforms (``x' = s R x + T`` as a 4x4 matrix) applied to points and cameras.

Used to move cameras and ground truth between frames: a synthetic object's own frame, the dataset's
GT frame (DTU mm world, TnT GT), the COLMAP frame and the normalised training frame. All in float64.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gsbench.data.camera import Camera


def similarity(scale: float = 1.0, rotation: np.ndarray | None = None, translation=(0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4 matrix ``[[s R, T], [0, 1]]``."""
    m = np.eye(4)
    m[:3, :3] = scale * (np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64))
    m[:3, 3] = np.asarray(translation, dtype=np.float64)
    return m


def decompose(m: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """``(s, R, T)`` of a similarity matrix; ``s = det(M[:3,:3])^(1/3)``."""
    s = float(np.cbrt(np.linalg.det(m[:3, :3])))
    return s, m[:3, :3] / s, m[:3, 3].copy()


def transform_points(m: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 similarity to (N,3) points."""
    return np.asarray(points, dtype=np.float64) @ m[:3, :3].T + m[:3, 3]


def transform_camera(camera: Camera, m: np.ndarray) -> Camera:
    """The same physical camera with its world re-expressed by ``x_new = s R x + T``.

    Camera-space coordinates scale with the world (depths are in the new units):
    ``R' = R Rᵀ_m``, ``t' = s t - R' T``. Intrinsics and image size are unchanged.
    """
    s, rot, trans = decompose(m)
    r_new = camera.R @ rot.T
    return replace(camera, R=r_new, t=s * camera.t - r_new @ trans)
