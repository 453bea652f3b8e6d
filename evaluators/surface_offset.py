"""Signed offset of a reconstructed surface from the exact one, in pixel footprints (built-in synthetic scenes),
as docs/evaluation.md §8 states it: Chamfer and F1 are unsigned, this says which way the error goes.

``s(p) = sign((p − q)·n_q)·|p − q|`` for area samples p of the mesh, q the closest point of the exact surface and
n_q its outward normal (positive outside); the footprint f = median over cameras of ‖C − c‖ / f_x at the
resolution the scene was loaded with; only samples with ``|s| < gate_px·f`` count.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from gsbench.data.camera import Scene
from gsbench.errors import EvaluationError, import_open3d
from gsbench.evaluators import pointsets
from gsbench.evaluators.base import Diagnostics, Evaluator, MetricInfo, check_files
from gsbench.evaluators.geometry import load_geometry, to_dataset_frame

GT_MESH = "gt_mesh.ply"


@dataclass(frozen=True)
class OffsetOptions:
    n_samples: int = 100_000
    seed: int = 0
    gate_px: float = 5.0
    footprint: float | None = None  # dataset units per pixel; None: from the scene's cameras
    frame: str = "normalised"


def gt_mesh_file(scene: Scene) -> Path:
    """``gt_mesh.ply`` beside the scene's images (written by the synthetic generator only)."""
    return Path(scene.root) / GT_MESH


def pixel_footprint(scene: Scene, centre_dataset: np.ndarray) -> float:
    """Median over cameras of ‖C − c‖ / f_x, in dataset units (module docstring)."""
    centre = scene.normalisation.invert(centre_dataset[None])[0]
    per_view = [np.linalg.norm(cam.center - centre) / cam.fx for cam in scene.cameras]
    return float(np.median(per_view)) * float(scene.normalisation.scale)


def signed_distances(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``sign((p − q)·n_q)|p − q|`` to the closest point q of the mesh (outward triangle normals n_q)."""
    o3d = import_open3d()
    # float32 ray-casting scene: shift to the mesh centre so large coordinates (UTM-like) keep precision
    origin = vertices.mean(axis=0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((vertices - origin).astype(np.float32)),
                        o3d.core.Tensor(triangles.astype(np.uint32)))
    ans = scene.compute_closest_points(o3d.core.Tensor((points - origin).astype(np.float32)))
    closest = ans["points"].numpy().astype(np.float64) + origin
    normals = ans["primitive_normals"].numpy().astype(np.float64)
    delta = points - closest
    return np.sign(np.sum(delta * normals, axis=1)) * np.linalg.norm(delta, axis=1)


class SurfaceOffset(Evaluator):
    """Signed distance of the mesh to the exact object surface, in pixel footprints."""

    name = "surface_offset"
    version = 1
    memory_per_face = 270
    requires = ("mesh",)
    metrics = {
        "offset_median_px": MetricInfo(False, "px", "median signed distance to the exact surface / pixel footprint "
                                                    "(< 0: inside); closer to 0 is better"),
        "offset_mean_px": MetricInfo(False, "px", "mean signed distance / pixel footprint"),
        "offset_abs_median_px": MetricInfo(False, "px", "median unsigned distance / pixel footprint"),
        "offset_median": MetricInfo(False, "dataset units", "median signed distance (DTU: mm)"),
        "offset_gated_fraction": MetricInfo(True, "", "fraction of mesh samples within gate_px of the object"),
    }
    Options = OffsetOptions

    def validate(self, scene: Scene) -> None:
        check_files(self.name, {"exact surface": gt_mesh_file(scene)},
                    "surface_offset needs the exact surface, which only built-in synthetic scenes have "
                    "(gsbench scene make NAME); drop surface_offset from eval.evaluators for other scenes")

    def evaluate(self, mesh, scene: Scene, **options) -> dict:
        opts = self.options(**options)
        diag = Diagnostics()
        with diag.phase("load"):
            self.validate(scene)
            geo = load_geometry(mesh, need_faces=True)
            verts = to_dataset_frame(geo.vertices, scene, opts.frame)
            gt = trimesh.load(gt_mesh_file(scene), process=False)
            gt_v, gt_f = np.asarray(gt.vertices, np.float64), np.asarray(gt.faces, np.int64)
            footprint = opts.footprint or pixel_footprint(scene, (gt_v.min(axis=0) + gt_v.max(axis=0)) / 2)
            if not (np.isfinite(footprint) and footprint > 0):
                raise EvaluationError(f"surface_offset: pixel footprint {footprint} is not positive; "
                                      "fix: pass footprint= (dataset units per pixel)")
        with diag.phase("sample"):
            try:
                samples, _ = pointsets.sample_surface(verts, geo.faces, opts.n_samples, opts.seed)
            except ValueError as exc:
                raise EvaluationError(f"surface_offset: {geo.label}: {exc}") from exc
        with diag.phase("distance"):
            s = signed_distances(samples, gt_v, gt_f) / footprint
        gated = np.abs(s) < opts.gate_px
        if not gated.any():
            raise EvaluationError(f"surface_offset: no sample of {geo.label} lies within {opts.gate_px} px of the "
                                  "exact surface; wrong frame or units (fix: check frame= and the scene)")
        sg = s[gated]
        diag.data.update(samples=len(s), footprint=footprint, gt_file=str(gt_mesh_file(scene)))
        return {
            "metrics": {
                "offset_median_px": float(np.median(sg)),
                "offset_mean_px": float(sg.mean()),
                "offset_abs_median_px": float(np.median(np.abs(sg))),
                "offset_median": float(np.median(sg) * footprint),
                "offset_gated_fraction": float(gated.mean()),
            },
            "protocol": self.protocol(opts) | {"footprint": footprint},
            "diagnostics": diag.finish(),
        }
