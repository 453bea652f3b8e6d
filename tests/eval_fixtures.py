"""Tiny ground-truth fixtures in the official DTU and TnT layouts, built analytically in a tmp dir.

Independent of gsbench.data's loaders and synthetic scenes: Scenes are constructed directly.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import scipy.io
import trimesh

from gsbench.data.camera import Camera, GroundTruth, Normalisation, Scene
from gsbench.evaluators.gt_io import write_log


def fibonacci_sphere(n: int, radius: float, center=(0.0, 0.0, 0.0)) -> np.ndarray:
    """``n`` near-uniform points on a sphere (golden-angle spiral)."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(1 - z**2)
    phi = np.pi * (3 - np.sqrt(5)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1) * radius + np.asarray(center)


def write_points_ply(path: Path, points: np.ndarray, normals: np.ndarray | None = None) -> None:
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(normals)
    path.parent.mkdir(parents=True, exist_ok=True)
    o3d.io.write_point_cloud(str(path), pcd)


def look_at(eye, target=(0, 0, 0), width=80, height=60, focal=70.0, name="") -> Camera:
    """An OpenCV camera at ``eye`` looking at ``target`` (world z up)."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    K = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]])
    return Camera(K=K, R=R, t=-R @ eye, width=width, height=height, name=name)


def ring_cameras(n: int, radius: float, center=(0.0, 0.0, 0.0), **kw) -> list[Camera]:
    """``n`` cameras on a tilted ring around ``center``, looking at it."""
    c = np.asarray(center, float)
    out = []
    for k in range(n):
        a = 2 * np.pi * k / n
        h = 0.6 * np.sin(3 * a)
        eye = c + radius * np.array([np.cos(a), np.sin(a), h]) / np.sqrt(1 + h * h)
        out.append(look_at(eye, c, name=f"{k:03d}", **kw))
    return out


def similarity(scale: float, axis, angle: float, translation) -> np.ndarray:
    """4x4 ``x -> s R x + t``, R a rotation of ``angle`` about ``axis``."""
    R = trimesh.transformations.rotation_matrix(angle, axis)[:3, :3]
    m = np.eye(4)
    m[:3, :3] = scale * R
    m[:3, 3] = translation
    return m


def transform_cameras(cameras: list[Camera], m: np.ndarray) -> list[Camera]:
    """Cameras of the world mapped by the similarity ``m`` (same images, new world frame)."""
    s = np.cbrt(np.linalg.det(m[:3, :3]))
    rot = m[:3, :3] / s
    out = []
    for cam in cameras:
        center = m[:3, :3] @ cam.center + m[:3, 3]
        R = cam.R @ rot.T
        out.append(Camera(K=cam.K, R=R, t=-R @ center, width=cam.width, height=cam.height, name=cam.name))
    return out


# ----------------------------------------------------------------------------- DTU

DTU_CENTER = np.array([5.0, -3.0, 620.0])  # mm, DTU world
DTU_RADIUS = 20.0  # mm
DTU_SCALE = 25.0  # normalised -> mm
DTU_SCAN = 7


def make_dtu_gt(root: Path, plane_z: float | None = None, obs_lower_half: bool = True) -> Path:
    """DTU evaluation layout: STL sphere points at ~0.2 mm spacing, ObsMask over BB, Plane.

    ``plane_z``: the ground plane height (default 2 mm below the sphere); ``obs_lower_half=False``
    clears the ObsMask below the sphere centre.
    """
    n = int(round(4 * np.pi * DTU_RADIUS**2 / 0.04))
    write_points_ply(root / "Points" / "stl" / f"stl{DTU_SCAN:03d}_total.ply", fibonacci_sphere(n, DTU_RADIUS, DTU_CENTER))
    res = 2.0
    bb = np.stack([DTU_CENTER - DTU_RADIUS - 5, DTU_CENTER + DTU_RADIUS + 5])
    shape = tuple(int(v) for v in np.round((bb[1] - bb[0]) / res) + 1)
    obs = np.ones(shape, dtype=np.uint8)
    if not obs_lower_half:
        obs[:, :, : int(np.round((DTU_CENTER[2] - bb[0, 2]) / res))] = 0
    (root / "ObsMask").mkdir(parents=True, exist_ok=True)
    scipy.io.savemat(root / "ObsMask" / f"ObsMask{DTU_SCAN}_10.mat", {"ObsMask": obs, "BB": bb, "Res": np.array([[res]])})
    z0 = DTU_CENTER[2] - DTU_RADIUS - 2 if plane_z is None else plane_z
    scipy.io.savemat(root / "ObsMask" / f"Plane{DTU_SCAN}.mat", {"P": np.array([[0.0], [0.0], [1.0], [-z0]])})
    return root


def dtu_scene(gt_root: Path, masks: list[np.ndarray] | None = None) -> Scene:
    """A DTU-like Scene: 8 cameras at radius 3 (normalised), all-true masks unless given."""
    cams = ring_cameras(8, 3.0)
    if masks is None:
        masks = [np.ones((c.height, c.width), bool) for c in cams]
    return Scene(
        name=f"scan{DTU_SCAN}", fmt="dtu", root=gt_root, cameras=cams,
        images=[np.zeros((c.height, c.width, 3), np.float32) for c in cams], masks=masks,
        normalisation=Normalisation(scale=DTU_SCALE, center=DTU_CENTER.copy(), radius=1.0),
        gt=GroundTruth(kind="dtu", root=gt_root, name=f"scan{DTU_SCAN}", scan=DTU_SCAN),
    )


def dtu_sphere_mesh(radius_mm: float = DTU_RADIUS, subdivisions: int = 5) -> trimesh.Trimesh:
    """An icosphere of ``radius_mm`` around the DTU centre, in the scene's normalised frame."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius_mm / DTU_SCALE)
    return trimesh.Trimesh(m.vertices, m.faces, process=False)


# ----------------------------------------------------------------------------- TnT

TNT_NAME = "Ball"
TNT_TAU = 0.05
TNT_RADIUS = 1.0  # COLMAP frame
TNT_TRANS = similarity(1.5, [1, 2, 3], 0.4, [0.3, -0.2, 0.5])  # COLMAP -> GT
TNT_NORM = Normalisation(scale=2.0, center=np.array([0.1, 0.0, -0.05]), radius=1.0)  # normalised -> COLMAP


def make_tnt_gt(root: Path, n_points: int = 60_000) -> Path:
    """TnT GT layout: sphere points (GT frame), crop json, trans.txt, reference COLMAP .log."""
    root.mkdir(parents=True, exist_ok=True)
    pts = fibonacci_sphere(n_points, TNT_RADIUS)
    gt = pts @ TNT_TRANS[:3, :3].T + TNT_TRANS[:3, 3]
    write_points_ply(root / f"{TNT_NAME}.ply", gt)
    np.savetxt(root / f"{TNT_NAME}_trans.txt", TNT_TRANS)
    c, h = TNT_TRANS[:3, 3], 1.5 * TNT_RADIUS + 0.2
    crop = {"class_name": "SelectionPolygonVolume", "orthogonal_axis": "Z", "axis_min": c[2] - h, "axis_max": c[2] + h,
            "bounding_polygon": [[c[0] - h, c[1] - h, 0], [c[0] + h, c[1] - h, 0], [c[0] + h, c[1] + h, 0], [c[0] - h, c[1] + h, 0]],
            "version_major": 1, "version_minor": 0}
    (root / f"{TNT_NAME}.json").write_text(json.dumps(crop))
    write_log(root / f"{TNT_NAME}_COLMAP_SfM.log", np.array([cam.camera_to_world for cam in ring_cameras(20, 4.0)]))
    return root


def tnt_scene(gt_root: Path, world: np.ndarray | None = None) -> Scene:
    """The scene whose cameras match the reference log; ``world`` re-expresses it in another frame."""
    colmap_cams = ring_cameras(20, 4.0)
    cams = transform_cameras(colmap_cams, np.diag([1 / TNT_NORM.scale] * 3 + [1]) @ _translate(-TNT_NORM.center))
    if world is not None:
        cams = transform_cameras(cams, world)
    return Scene(
        name=TNT_NAME, fmt="tnt", root=gt_root, cameras=cams,
        images=[np.zeros((c.height, c.width, 3), np.float32) for c in cams],
        normalisation=TNT_NORM, gt=GroundTruth(kind="tnt", root=gt_root, name=TNT_NAME, tau=TNT_TAU),
    )


def _translate(t) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m


def tnt_sphere_mesh(offset: float = 0.0, world: np.ndarray | None = None, subdivisions: int = 5) -> trimesh.Trimesh:
    """The TnT sphere in the normalised frame; vertices moved radially by ``+-offset`` (GT units) with
    the sign of ``x y z`` (octant pattern, so no similarity can undo it); ``world`` maps the result."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=TNT_RADIUS)
    v = m.vertices.copy()
    gt_scale = np.cbrt(np.linalg.det(TNT_TRANS[:3, :3]))
    sign = np.sign(v[:, 0] * v[:, 1] * v[:, 2])
    v = v * (1 + sign * offset / gt_scale / TNT_RADIUS)[:, None]
    v = TNT_NORM.invert(v)
    if world is not None:
        v = v @ world[:3, :3].T + world[:3, 3]
    return trimesh.Trimesh(v, m.faces, process=False)


def grid_samples_loop(vertices, faces, density):
    """Per-triangle loop written straight from docs/evaluation.md §2.2."""
    out = []
    for f in faces:
        a, b, c = vertices[f]
        v1, v2 = b - a, c - a
        l1, l2, area2 = np.linalg.norm(v1), np.linalg.norm(v2), np.linalg.norm(np.cross(v1, v2))
        if area2 == 0:
            continue
        thr = density * np.sqrt(l1 * l2 / area2)
        n1, n2 = int(np.floor(l1 / thr)), int(np.floor(l2 / thr))
        for i in range(n1 + 1):
            for j in range(n2 + 1):
                k1, k2 = (i + 0.5) / max(n1, 1e-7), (j + 0.5) / max(n2, 1e-7)
                if k1 + k2 < 1:
                    out.append(a + k1 * v1 + k2 * v2)
    return np.array(out).reshape(-1, 3)
