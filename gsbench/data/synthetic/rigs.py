"""Camera rigs for synthetic scenes, in the object frame (z up, object at the origin).

- ``cap``: DTU-like. Directions on a spherical cap (Fibonacci spiral, even coverage) of half-angle
  40 degrees about an axis 40 degrees above the horizon facing the object's front (+y), so camera
  elevations span about 0-80 degrees, like DTU's robot-arm positions on one side of the object.
- ``ring``: TnT-like. A two-turn helix all around the object at elevations 5-40 degrees, ordered
  along the path (the trajectory order).
- ``band``: grazing views, elevations 2-20 degrees all around (Fibonacci), for thin structures.

Each camera looks at the origin plus a small random offset (seeded), from ``distance`` x (1 ± 5%).
Orientation: OpenCV (x right, y down, z forward), image "up" is world +z.

The datasets' own rigs (`gsbench.data.reference_rigs`; docs/scenes.md §2):

- ``dtu``: DTU's 49 cameras and intrinsics, exactly, in IDR's normalised frame of scan 65. The object
  frame is set in that frame with its origin at the sphere's centre, z up and +y towards the cameras
  (`dtu_object_axes`); ``distance`` (the cameras' mean distance, in object radii) sets the object's size.
- ``barn``: Tanks-and-Temples Barn's intrinsics and floor plan: every k-th camera of its trajectory keeps
  its horizontal offset from the crop centre in crop radii, mapped onto the scene's crop region; the
  heights follow the ``ring`` rig's elevations and each camera looks at the object (`barn_cameras`).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from gsbench.data.camera import Camera
from gsbench.data.frame import Region
from gsbench.data.reference_rigs import ReferenceRig
from gsbench.data.similarity import similarity, transform_camera
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
REAL_RIGS = {"dtu": "dtu", "barn": "tnt"}  # the datasets' own rigs -> the layout they belong to


def make_rig(kind: str, n: int, distance: float, jitter: float, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` world-to-camera poses ``(R, t)``; ``jitter`` is the look-at offset scale (object units)."""
    if kind not in RIGS:
        raise DataError(f"unknown camera rig {kind!r}; expected one of {sorted(RIGS) + sorted(REAL_RIGS)}")
    poses = []
    for d in RIGS[kind](n):
        eye = d * distance * rng.uniform(0.95, 1.05)
        poses.append(look_at(eye, rng.normal(scale=jitter, size=3)))
    return poses


def dtu_object_axes(cameras: list[Camera]) -> np.ndarray:
    """Rotation whose columns are the object frame's x, y, z in the frame of ``cameras``: z (up) is the
    direction least seen along the cameras' image x axes (DTU's views are upright: the smallest eigenvector
    of Σ xᵢxᵢᵀ, signed towards the cameras), y the cameras' mean direction from the origin made horizontal."""
    x_axes = np.array([c.R[0] for c in cameras])
    up = np.linalg.eigh(x_axes.T @ x_axes)[1][:, 0]
    centres = np.array([c.center for c in cameras])
    if up @ centres.mean(axis=0) < 0:
        up = -up
    front = centres.mean(axis=0) - (centres.mean(axis=0) @ up) * up
    front /= np.linalg.norm(front)
    return np.stack([np.cross(front, up), front, up], axis=1)


def dtu_cameras(reference: ReferenceRig, width: int, height: int, radius: float) -> tuple[Callable[[float], list[Camera]], Callable[[float], np.ndarray]]:
    """``(cameras_at, object_to_training)``: DTU's cameras in the object frame when their mean distance is
    ``distance`` object radii (object radius ``radius``, object units), and the object-to-training-frame
    similarity that places the object there (module docstring)."""
    training = [c.scaled(width / c.width) for c in reference.training_cameras]
    if training[0].height != height:
        raise DataError(f"image size {width}x{height}: DTU's rig is {reference.cameras[0].width}x{reference.cameras[0].height}; "
                        "fix: a size with its 4:3 aspect, e.g. --res 400 300")
    axes = dtu_object_axes(training)
    mean_distance = float(np.mean([np.linalg.norm(c.center) for c in training]))

    def object_to_training(distance: float) -> np.ndarray:
        return similarity(mean_distance / (distance * radius), axes)

    def cameras_at(distance: float) -> list[Camera]:
        to_object = np.linalg.inv(object_to_training(distance))
        return [transform_camera(c, to_object) for c in training]

    return cameras_at, object_to_training


def barn_cameras(reference: ReferenceRig, region: Region, views: int, width: int, height: int, jitter: float,
                 rng: np.random.Generator) -> list[Camera]:
    """``views`` cameras in the object frame on Barn's floor plan (module docstring): trajectory frames
    ``round(linspace(0, n - 1, views))``, each at its horizontal offset from Barn's crop centre scaled by the
    ratio of the crop radii, at the ``ring`` rig's elevation above the object's centre (the origin), looking
    at the origin plus a seeded offset of scale ``jitter``; Barn's intrinsics scaled to ``width``."""
    first = reference.cameras[0]
    K = first.scaled(width / first.width).K  # Barn's one lens
    if round(first.height * width / first.width) != height:
        raise DataError(f"image size {width}x{height}: Barn's frames are {first.width}x{first.height}; fix: a 16:9 size")
    picks = np.round(np.linspace(0, len(reference.cameras) - 1, views)).astype(int)
    elevations = np.arcsin(_ring(views)[:, 2])
    cameras = []
    for k, (i, elevation) in enumerate(zip(picks, elevations)):
        offset = (reference.cameras[i].center - reference.region.centre)[:2] / reference.region.radius * region.radius
        ground = region.centre[:2] + offset
        R, t = look_at(np.array([*ground, np.linalg.norm(ground) * np.tan(elevation)]), rng.normal(scale=jitter, size=3))
        cameras.append(Camera(K=K, R=R, t=t, width=width, height=height, name=f"{k:06d}.png"))
    return cameras
