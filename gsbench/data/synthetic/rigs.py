"""Camera rigs for synthetic scenes, in the object frame (z up, object at the origin).

- ``cap``: DTU-like. Directions on a spherical cap (Fibonacci spiral, even coverage) of half-angle
  40 degrees about an axis 40 degrees above the horizon facing the object's front (+y), so camera
  elevations span about 0-80 degrees, like DTU's robot-arm positions on one side of the object.
- ``ring``: TnT-like. A two-turn helix all around the object at elevations 5-40 degrees, ordered
  along the path (the trajectory order).
- ``band``: grazing views, elevations 2-20 degrees all around (Fibonacci), for thin structures.

Each camera looks at the origin plus a small random offset (seeded), from ``distance`` x (1 ± 5%).
Orientation: OpenCV (x right, y down, z forward), image "up" is world +z.
"""

from __future__ import annotations

import numpy as np

from gsbench.errors import DataError

GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera ``(R, t)`` of a camera at ``eye`` looking at ``target`` with world ``up`` up."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(-np.asarray(up, dtype=np.float64), z)
    if np.linalg.norm(x) < 1e-6:  # looking straight along up: any horizontal x will do
        x = np.cross(np.array([0.0, 1.0, 0.0]), z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ eye


def _from_elevation_azimuth(elev: np.ndarray, azim: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim), np.sin(elev)], axis=1)


def _cap(n: int) -> np.ndarray:
    half = np.radians(40.0)
    k = np.arange(n) + 0.5
    theta = np.arccos(1.0 - k / n * (1.0 - np.cos(half)))
    phi = k * GOLDEN_ANGLE
    local = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=1)
    axis = _from_elevation_azimuth(np.radians([40.0]), np.radians([90.0]))[0]
    e1 = np.cross(axis, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    return local @ np.stack([e1, np.cross(axis, e1), axis])


def _ring(n: int) -> np.ndarray:
    s = np.arange(n) / n
    return _from_elevation_azimuth(np.radians(5.0 + 35.0 * s), 4 * np.pi * s)


def _band(n: int) -> np.ndarray:
    k = np.arange(n) + 0.5
    return _from_elevation_azimuth(np.radians(2.0 + 18.0 * k / n), k * GOLDEN_ANGLE)


RIGS = {"cap": _cap, "ring": _ring, "band": _band}


def make_rig(kind: str, n: int, distance: float, jitter: float, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` world-to-camera poses ``(R, t)``; ``jitter`` is the look-at offset scale (object units)."""
    if kind not in RIGS:
        raise DataError(f"unknown camera rig {kind!r}; expected one of {sorted(RIGS)}")
    poses = []
    for d in RIGS[kind](n):
        eye = d * distance * rng.uniform(0.95, 1.05)
        poses.append(look_at(eye, rng.normal(scale=jitter, size=3)))
    return poses
