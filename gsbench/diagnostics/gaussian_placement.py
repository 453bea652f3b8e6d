"""`gsbench gaussians`: where a finished run's Gaussians are, against its synthetic scene's exact surfaces.

Under a Gaussian budget (``train.max_gaussians``) what a method spends Gaussians on decides how many are
left for the object. For a run on a built-in synthetic scene, each Gaussian centre μ (mapped to the
dataset frame) is placed by its unsigned distances d_o to the object's surface (``gt_mesh.ply``) and
d_s to the nearest surface of anything the images show (``gt_scene_mesh.ply``: object and
environment; the object alone on a scene without environment):

- ``object``:      d_o ≤ τ;
- ``environment``: d_o > τ and d_s ≤ τ (the table, the room, the ground, the props);
- ``free space``:  d_s > τ (between or behind surfaces: floaters, or blobs that paint far background).

τ (``within``, dataset units) defaults to `WITHIN_OF_DIAGONAL` of the object's bounding-box diagonal
(2.0–2.6 mm for the DTU-like objects, about the 2 mm of their pixel footprints at the cpu preset's
200x150). Each region gets its Gaussian count, its share of the count and its share of the total
opacity Σ σ(o_i) (a faint Gaussian contributes less to any image).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import trimesh

from gsbench.data.synthetic.generator import GT_MESH_NAME, SCENE_MESH_NAME
from gsbench.diagnostics.text_table import aligned
from gsbench.errors import ConfigError, GsbenchError, import_open3d
from gsbench.runs.finished_run import load_finished_run

WITHIN_OF_DIAGONAL = 0.015
REGIONS = ("object", "environment", "free space")


def _distances(mesh_path: Path, points: np.ndarray) -> np.ndarray:
    """Unsigned distance of each point (N,3) to the triangle mesh at ``mesh_path`` (open3d raycasting scene)."""
    o3d = import_open3d()  # with the clear error when its system library is missing

    mesh = o3d.t.io.read_triangle_mesh(str(mesh_path))
    if mesh.triangle.indices.shape[0] == 0:
        raise GsbenchError(f"{mesh_path}: no triangles; fix: regenerate the scene (gsbench scene make NAME)")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh)
    return scene.compute_distance(o3d.core.Tensor(np.ascontiguousarray(points, np.float32))).numpy().astype(np.float64)


def place(d_object: np.ndarray, d_scene: np.ndarray, opacity: np.ndarray, within: float) -> dict:
    """``{region: {"count", "share", "opacity_share"}}`` for the distances and opacities of N Gaussians
    (module docstring); shares are of N and of Σ opacity (0 when N or Σ opacity is 0)."""
    if not within > 0:
        raise ConfigError(f"--within must be a positive distance (dataset units), got {within}")
    near_object = d_object <= within
    masks = {"object": near_object, "environment": ~near_object & (d_scene <= within),
             "free space": ~near_object & (d_scene > within)}
    n, total = len(opacity), float(np.sum(opacity))
    return {name: {"count": int(mask.sum()), "share": float(mask.sum()) / n if n else 0.0,
                   "opacity_share": float(opacity[mask].sum()) / total if total > 0 else 0.0}
            for name, mask in masks.items()}


def run_placement(folder, within: float | None = None) -> tuple[dict, float]:
    """`place` of the Gaussians of the finished run in ``folder`` and the τ used (module docstring)."""
    _, scene, method = load_finished_run(folder, "gsbench gaussians", load_images=False)
    object_mesh, scene_mesh = Path(scene.root) / GT_MESH_NAME, Path(scene.root) / SCENE_MESH_NAME
    if not object_mesh.is_file():
        raise GsbenchError(f"{object_mesh} not found: `gsbench gaussians` needs a built-in synthetic scene's exact "
                           "surfaces; fix: use it on runs of synthetic/* scenes (a real capture has no exact surface)")
    if not scene_mesh.is_file():
        scene_mesh = object_mesh
    with torch.no_grad():
        means = scene.normalisation.apply(method.gaussians.means.double().numpy())
        opacity = method.gaussians.opacities.double().numpy().reshape(-1)
    if within is None:
        bounds = trimesh.load(object_mesh, process=False).bounds
        within = WITHIN_OF_DIAGONAL * float(np.linalg.norm(bounds[1] - bounds[0]))
    return place(_distances(object_mesh, means), _distances(scene_mesh, means), opacity, within), within


def format_placement(regions: dict) -> str:
    """A text table of `place`'s regions."""
    head = ["region", "Gaussians", "share", "opacity share"]
    body = [[name, f"{r['count']:,}", f"{r['share']:.3f}", f"{r['opacity_share']:.3f}"] for name, r in regions.items()]
    return aligned(head, body)
