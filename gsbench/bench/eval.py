"""Fixed evaluator workloads (``gsbench bench eval``).

DTU (`run_eval_benchmark`): dtu_chamfer (mesh mode, with culling) on a large synthetic sphere. The GT
is ``n_gt`` points on a sphere at ~0.2 mm spacing (the radius follows from the count), written in the
DTU layout to a temporary folder; the mesh is a latitude-longitude sphere with ``n_vertices`` vertices
and seeded radial noise (sigma 0.1 mm); the scene has ``n_views`` 1600x1200 cameras on a ring with
disc masks around the sphere's silhouette. Reported: seconds per evaluator phase, peak RSS and the
number of threads the KD-tree queries may use.

TnT (`run_tnt_benchmark`): tnt_f1 on a unit-radius sphere of ``n_gt`` GT points (tau = 0.5 x their
spacing, the real scenes' ratio of tau to the laser scan's density being of that order), in the TnT
layout (identity ``_trans.txt``, a ring trajectory), for two meshes of ``n_vertices`` vertices: a
**partial** one (the upper half of the sphere: half the GT has no reconstruction near it) and a
**noisy** one (radial noise of sigma tau). Reported per mesh: the whole evaluation's phase seconds, and
the scoring of the official point set timed twice, its nearest-neighbour queries capped at tau (what
the evaluator does) and uncapped (what it did before), with the fractions of both (equal).
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.io
import trimesh

from gsbench.data.camera import Camera, GroundTruth, Normalisation, Scene
from gsbench.errors import import_open3d
from gsbench.evaluators import gt_io, tnt_f1
from gsbench.evaluators.dtu_chamfer import DTUChamfer
from gsbench.evaluators.tnt_f1 import TnTF1
from gsbench.resources import peak_rss_bytes

SPACING = 0.2  # mm, GT point spacing
SCAN = 1


def _fibonacci_sphere(n: int, radius: float) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    r = np.sqrt(1 - z**2)
    phi = np.pi * (3 - np.sqrt(5)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1) * radius


def latlong_sphere(n_vertices: int, radius: float, noise: float, seed: int):
    """(vertices, faces) of a latitude-longitude sphere with ~``n_vertices`` vertices and radial noise."""
    n_lat = max(2, int(round(np.sqrt(n_vertices / 2))))
    n_lon = max(3, int(round(n_vertices / n_lat)))
    theta = np.pi * (np.arange(n_lat) + 0.5) / n_lat
    phi = 2 * np.pi * np.arange(n_lon) / n_lon
    t, p = np.meshgrid(theta, phi, indexing="ij")
    v = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    v = np.vstack([v, [[0, 0, 1.0], [0, 0, -1.0]]])
    r = radius + np.random.default_rng(seed).normal(0, noise, len(v))
    v *= r[:, None]
    idx = np.arange(n_lat * n_lon).reshape(n_lat, n_lon)
    a, b = idx[:-1], np.roll(idx[:-1], -1, axis=1)
    c, d = idx[1:], np.roll(idx[1:], -1, axis=1)
    quads = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    north, south = len(v) - 2, len(v) - 1
    top = np.stack([np.full(n_lon, north), idx[0], np.roll(idx[0], -1)], -1)
    bottom = np.stack([np.full(n_lon, south), np.roll(idx[-1], -1), idx[-1]], -1)
    return v, np.concatenate([quads, top, bottom]).astype(np.int64)


def _write_gt(root: Path, n_gt: int, radius: float) -> None:
    o3d = import_open3d()
    stl = root / "Points" / "stl"
    stl.mkdir(parents=True)
    o3d.io.write_point_cloud(str(stl / f"stl{SCAN:03d}_total.ply"),
                             o3d.geometry.PointCloud(o3d.utility.Vector3dVector(_fibonacci_sphere(n_gt, radius))))
    res = 4.0
    bb = np.array([[-radius - 10] * 3, [radius + 10] * 3])
    shape = tuple(int(s) for s in np.round((bb[1] - bb[0]) / res) + 1)
    (root / "ObsMask").mkdir()
    scipy.io.savemat(root / "ObsMask" / f"ObsMask{SCAN}_10.mat",
                     {"ObsMask": np.ones(shape, np.uint8), "BB": bb, "Res": np.array([[res]])})
    scipy.io.savemat(root / "ObsMask" / f"Plane{SCAN}.mat", {"P": np.array([[0.0], [0.0], [1.0], [radius + 5]])})


def _ring_scene(root: Path, n_views: int, radius_norm: float, scale: float) -> Scene:
    w, h, f, dist = 1600, 1200, 1500.0, 3.0
    cams, masks = [], []
    yy, xx = np.mgrid[0:h, 0:w]
    silhouette = f * radius_norm / np.sqrt(dist**2 - radius_norm**2)
    disc = (xx + 0.5 - w / 2) ** 2 + (yy + 0.5 - h / 2) ** 2 <= (1.02 * silhouette) ** 2
    for k in range(n_views):
        a = 2 * np.pi * k / n_views
        eye = dist * np.array([np.cos(a), np.sin(a), 0.3 * np.sin(3 * a)])
        z = -eye / np.linalg.norm(eye)
        x = np.cross(z, [0, 0, 1.0])
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        cam = Camera(K=np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]]), R=R, t=-R @ eye, width=w, height=h, name=f"{k:03d}")
        masks.append(disc)
        cams.append(cam)
    return Scene(name=f"scan{SCAN}", fmt="dtu", root=root, cameras=cams, images=[], masks=masks,
                 normalisation=Normalisation(scale=scale, center=np.zeros(3), radius=1.0),
                 gt=GroundTruth(kind="dtu", root=root, name=f"scan{SCAN}", scan=SCAN))


def run_eval_benchmark(n_vertices: int = 1_000_000, n_gt: int = 2_000_000, seed: int = 0, n_views: int = 49) -> dict:
    """Time dtu_chamfer on a synthetic ``n_vertices`` mesh against ``n_gt`` GT points; see the module doc."""
    radius = float(np.sqrt(n_gt * SPACING**2 / (4 * np.pi)))
    scale = radius / 0.8  # the sphere fills 0.8 of the unit sphere in the normalised frame
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="gsbench_evalbench_") as tmp:
        root = Path(tmp)
        _write_gt(root, n_gt, radius)
        verts, faces = latlong_sphere(n_vertices, radius, noise=0.1, seed=seed)
        scene = _ring_scene(root, n_views, 0.8, scale)
        setup_s, setup_rss = time.perf_counter() - t0, peak_rss_bytes()
        mesh = trimesh.Trimesh(verts / scale, faces, process=False)
        result = DTUChamfer().evaluate(mesh, scene, seed=seed)
    diag = result["diagnostics"]
    return {
        "workload": {"n_vertices": len(verts), "n_faces": len(faces), "n_gt": n_gt, "n_views": n_views,
                     "radius_mm": radius, "sampled_points": diag["sampled_points"],
                     "downsampled_points": diag["downsampled_points"]},
        "threads": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "setup_seconds": round(setup_s, 3),
        "seconds": diag["seconds"],
        "total_seconds": diag["total_seconds"],
        "peak_rss_bytes_setup": setup_rss,
        "peak_rss_bytes": diag["peak_rss_bytes_total"],
        "metrics": result["metrics"],
    }


def _write_tnt_gt(root: Path, gt: np.ndarray, tau: float, n_views: int) -> Scene:
    """A TnT-layout GT folder (``Bench.ply``, crop ``.json``, identity ``_trans.txt``, ring trajectory
    ``_COLMAP_SfM.log``) and the matching scene (the GT frame is the scene frame)."""
    o3d = import_open3d()
    o3d.io.write_point_cloud(str(root / "Bench.ply"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(gt)))
    h = 1.5
    crop = {"class_name": "SelectionPolygonVolume", "orthogonal_axis": "Z", "axis_min": -h, "axis_max": h,
            "bounding_polygon": [[-h, -h, 0], [h, -h, 0], [h, h, 0], [-h, h, 0]], "version_major": 1, "version_minor": 0}
    (root / "Bench.json").write_text(json.dumps(crop))
    np.savetxt(root / "Bench_trans.txt", np.eye(4))
    scene = _ring_scene(root, n_views, 0.8, 1.0)
    scene.fmt, scene.name, scene.masks = "tnt", "Bench", None
    scene.gt = GroundTruth(kind="tnt", root=root, name="Bench", tau=tau)
    gt_io.write_log(root / "Bench_COLMAP_SfM.log", np.array([cam.camera_to_world for cam in scene.cameras]))
    return scene


def _time_scoring(mesh, scene, tau: float) -> dict:
    """The official point set's scoring (crop, voxel tau/2, both NN directions) capped and uncapped."""
    o3d = import_open3d()
    volume = gt_io.read_crop_volume(Path(scene.gt.root) / "Bench.json")
    gt = o3d.io.read_point_cloud(str(Path(scene.gt.root) / "Bench.ply"))
    t = np.asarray(volume.crop_point_cloud(gt).voxel_down_sample(tau / 2).points)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(mesh.vertices)))
    s = np.asarray(volume.crop_point_cloud(cloud).voxel_down_sample(tau / 2).points)
    out = {}
    for name, capped in (("capped", True), ("uncapped", False)):
        t0 = time.perf_counter()
        out[f"{name}_fractions"] = tnt_f1.precision_recall(s, t, tau, capped=capped)
        out[f"{name}_seconds"] = round(time.perf_counter() - t0, 3)
    out["source_points"], out["target_points"] = len(s), len(t)
    return out


def run_tnt_benchmark(n_vertices: int = 1_000_000, n_gt: int = 2_000_000, seed: int = 0, n_views: int = 20) -> dict:
    """Time tnt_f1 on a partial and a noisy sphere mesh against ``n_gt`` GT points; see the module doc."""
    spacing = float(np.sqrt(4 * np.pi / n_gt))
    tau = 0.5 * spacing
    verts, faces = latlong_sphere(n_vertices, 1.0, noise=0.0, seed=seed)
    upper = faces[verts[faces].mean(axis=1)[:, 2] > 0]
    noisy = verts * (1 + np.random.default_rng(seed).normal(0, tau, len(verts)))[:, None]
    meshes = {"partial": trimesh.Trimesh(verts, upper, process=False), "noisy": trimesh.Trimesh(noisy, faces, process=False)}
    result = {"workload": {"n_vertices": len(verts), "n_gt": n_gt, "tau": tau, "n_views": n_views}, "meshes": {}}
    with tempfile.TemporaryDirectory(prefix="gsbench_tntbench_") as tmp:
        scene = _write_tnt_gt(Path(tmp), _fibonacci_sphere(n_gt, 1.0), tau, n_views)
        for name, mesh in meshes.items():
            t0 = time.perf_counter()
            evaluated = TnTF1().evaluate(mesh, scene, frame="dataset")
            result["meshes"][name] = {"evaluate_seconds": round(time.perf_counter() - t0, 3),
                                      "seconds": evaluated["diagnostics"]["seconds"], "metrics": evaluated["metrics"],
                                      "scoring": _time_scoring(mesh, scene, tau)}
    return result
