"""Signed offset of a reconstructed surface from the exact one, in pixel footprints (synthetic scenes).

The official protocols (Chamfer, F1) are unsigned: a surface that sits one pixel inside the truth
and one that is noisy by a pixel score alike. This evaluator says which way the error goes, in the
unit that explains it — the footprint of one training pixel on the object. It needs the exact
surface, so it runs on built-in synthetic scenes only (their ``gt_mesh.ply``: the object, closed
and outward-oriented, in the dataset frame).

Definition:

- ``n_samples`` area-uniform samples p of the predicted mesh (seeded), mapped to the dataset frame.
- q = the closest point of the GT mesh to p, n_q the outward normal of its triangle;
  ``s(p) = sign((p − q)·n_q) · |p − q|`` (positive outside the object, negative inside).
- Pixel footprint ``f`` = median over the scene's cameras of ‖C − c‖ / f_x (C the camera centre,
  c the centre of the GT mesh's bounding box, f_x at the resolution the scene was loaded with —
  the training resolution in ``gsbench run``), in dataset units: the size of one pixel on the object.
- Only samples with ``|s| < gate_px · f`` count (default 5 px): floaters, the table and the
  background are not the object's surface and are left to Chamfer / F1.
- Metrics: median and mean of s / f (``offset_median_px``, ``offset_mean_px``), the median of |s| / f
  (``offset_abs_median_px``), the median of s in dataset units (DTU: mm), and the fraction of
  samples inside the gate (``offset_gated_fraction``).
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
