"""Normal consistency of a mesh against ground truth (evaluation.md §3, recommendation B), protocol v1.

Definition (Occupancy Networks ``im2mesh/eval.py`` style, with the distance gate of variant C):

- Sample ``n_samples`` area-uniform points with their face normals on the predicted mesh (seeded).
- GT: ``n_samples`` points with normals — sampled the same way on a GT mesh, or a seeded subset of
  the GT points, with the file's normals when it has them, else unoriented PCA normals from the
  ``k_pca`` nearest points of the **full** GT cloud (the open3d ``estimate_normals(KNN 20)`` formula).
- ``acc_n = mean_p |n_p . n_gt(NN_gt(p))|`` over predicted samples, ``comp_n = mean_g |n_g .
  n_pred(NN_pred(g))|`` over GT samples; the absolute value ignores orientation.
- Gated (the headline ``normal_consistency``): only pairs whose NN distance is ``< max_dist``, so
  holes and floaters (already counted by Chamfer / F-score) do not count twice. ``max_dist`` defaults
  to the scene's tau when it has one, else ``gate_factor`` x the median NN spacing of the GT samples.
  The ungated mean is reported as ``normal_consistency_ungated``.
- ``NC = (acc_n + comp_n) / 2``, in [0, 1].

GT by scene kind: ``dtu`` -> ``Points/stl/stl{scan:03d}_total.ply`` (mm world); ``tnt`` -> ``{name}.ply``
with the prediction mapped by ``{name}_trans.txt`` (no ICP refinement: assumes the reconstruction
frame is the reference COLMAP frame, as for 2DGS/GOF/RaDe-GS data); any other kind ->
``{root}/{name}.ply``, a mesh when it has faces, else points. ``gt_mesh=`` / ``gt_points=`` override.

Image-space normals (recommendation A) are `rendered_normal_similarity`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from gsbench.data.camera import Scene
from gsbench.errors import EvaluationError
from gsbench.evaluators import gt_io, pointsets
from gsbench.evaluators.base import Diagnostics, Evaluator, MetricInfo, check_files
from gsbench.evaluators.geometry import load_geometry, to_dataset_frame


@dataclass(frozen=True)
class NormalOptions:
    n_samples: int = 100_000
    seed: int = 0
    k_pca: int = 20
    max_dist: float | None = None  # gate in GT units; None: tau, else gate_factor x GT spacing
    gate_factor: float = 5.0
    gt_mesh: str | None = None
    gt_points: str | None = None
    frame: str = "normalised"


def gt_surface_file(scene: Scene) -> Path:
    """The GT file the scene's kind provides (see the module docstring)."""
    if scene.gt is None:
        raise EvaluationError(
            f"normal_similarity: scene '{scene.name}' has no ground truth ({scene.gt_missing or 'none found'}); "
            "fix: --gt PATH, the folder holding it (or the gt_mesh/gt_points options from Python)"
        )
    root = Path(scene.gt.root)
    if scene.gt.kind == "dtu":
        if scene.gt.scan is None:
            raise EvaluationError(f"normal_similarity: DTU scene '{scene.name}' has no scan number")
        return root / "Points" / "stl" / f"stl{scene.gt.scan:03d}_total.ply"
    return root / f"{scene.gt.name}.ply"


def _gt_samples(path: Path, as_mesh: bool | None, opts: NormalOptions) -> tuple[np.ndarray, np.ndarray, str]:
    """(points, unit normals, how) for the GT; ``as_mesh=None`` decides by whether the file has faces."""
    if as_mesh is not False:
        geo = load_geometry(path)
        if geo.is_mesh:
            pts, nrm = pointsets.sample_surface(geo.vertices, geo.faces, opts.n_samples, opts.seed + 1)
            return pts, nrm, "mesh samples"
        if as_mesh:
            raise EvaluationError(f"normal_similarity: gt_mesh {path} has no faces (fix: pass it as gt_points=)")
    pts, normals = gt_io.read_points(path, with_normals=True)
    rng = np.random.default_rng(opts.seed + 1)
    sub = np.sort(rng.choice(len(pts), opts.n_samples, replace=False)) if len(pts) > opts.n_samples else np.arange(len(pts))
    if normals is not None and np.isfinite(normals[sub]).all() and (np.linalg.norm(normals[sub], axis=1) > 0).all():
        return pts[sub], normals[sub] / np.linalg.norm(normals[sub], axis=1, keepdims=True), "file normals"
    return pts[sub], pointsets.pca_normals(pts, pts[sub], opts.k_pca), f"PCA normals (k={opts.k_pca})"


def _abs_cos(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(np.einsum("ij,ij->i", a, b))


def rendered_normal_similarity(pred_normals: np.ndarray, gt_normals: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean cosine ``n_pred . n_gt`` over ``mask`` for HxWx3 normal maps (evaluation.md §3 A).

    Both maps are normalised per pixel first; pixels where either normal has zero length are excluded.
    Signed (no absolute value): rendered and GT normals share an orientation convention.
    """
    p = np.asarray(pred_normals, np.float64)
    g = np.asarray(gt_normals, np.float64)
    if p.shape != g.shape or p.shape[-1] != 3:
        raise EvaluationError(f"normal maps must both be HxWx3, got {p.shape} and {g.shape}")
    pn, gn = np.linalg.norm(p, axis=-1), np.linalg.norm(g, axis=-1)
    valid = (pn > 0) & (gn > 0) & np.isfinite(pn) & np.isfinite(gn)
    if mask is not None:
        valid &= np.asarray(mask, bool)
    if not valid.any():
        raise EvaluationError("rendered_normal_similarity: the mask selects no pixel with valid normals")
    cos = np.einsum("ij,ij->i", p[valid] / pn[valid][:, None], g[valid] / gn[valid][:, None])
    return float(cos.mean())


class NormalSimilarity(Evaluator):
    """Gated normal consistency NC in [0, 1] between mesh and GT surface normals."""

    name = "normal_similarity"
    version = 1
    requires = ("mesh",)
    metrics = {
        "normal_consistency": MetricInfo(True, "", "mean |cos| of NN normal pairs closer than max_dist, both ways"),
        "normal_accuracy": MetricInfo(True, "", "gated mean |cos|, prediction -> GT"),
        "normal_completeness": MetricInfo(True, "", "gated mean |cos|, GT -> prediction"),
        "normal_consistency_ungated": MetricInfo(True, "", "NC over all NN pairs"),
    }
    Options = NormalOptions

    def validate(self, scene: Scene) -> None:
        check_files(self.name, {"GT surface": gt_surface_file(scene)},
                    "provide the scene's ground-truth points or mesh (--gt PATH), or the gt_mesh/gt_points options")

    def evaluate(self, mesh, scene: Scene, **options) -> dict:
        opts = self.options(**options)
        diag = Diagnostics()
        with diag.phase("load"):
            geo = load_geometry(mesh, need_faces=True)
            verts = to_dataset_frame(geo.vertices, scene, opts.frame)
            if opts.gt_mesh or opts.gt_points:
                path, as_mesh = Path(opts.gt_mesh or opts.gt_points), bool(opts.gt_mesh)
                if not path.is_file():
                    raise EvaluationError(f"normal_similarity: GT file not found: {path}")
            else:
                self.validate(scene)
                path, as_mesh = gt_surface_file(scene), (False if scene.gt.kind in ("dtu", "tnt") else None)
                if scene.gt.kind == "tnt":
                    trans = gt_io.read_matrix4(Path(scene.gt.root) / f"{scene.gt.name}_trans.txt")
                    verts = verts @ trans[:3, :3].T + trans[:3, 3]
        with diag.phase("sample"):
            try:
                p_pts, p_nrm = pointsets.sample_surface(verts, geo.faces, opts.n_samples, opts.seed)
            except ValueError as exc:
                raise EvaluationError(f"normal_similarity: {geo.label}: {exc}") from exc
            g_pts, g_nrm, how = _gt_samples(path, as_mesh, opts)
            diag.data.update(gt_file=str(path), gt_normals=how, pred_samples=len(p_pts), gt_samples=len(g_pts))
        with diag.phase("match"):
            g_tree = cKDTree(g_pts)
            d_p, i_p = pointsets.nn_indices(p_pts, g_tree)
            d_g, i_g = pointsets.nn_indices(g_pts, cKDTree(p_pts))
            cos_p, cos_g = _abs_cos(p_nrm, g_nrm[i_p]), _abs_cos(g_nrm, p_nrm[i_g])
            if opts.max_dist is not None:
                gate, gate_rule = opts.max_dist, "option"
            elif scene.gt is not None and scene.gt.tau:
                gate, gate_rule = float(scene.gt.tau), "tau"
            else:
                spacing = float(np.median(g_tree.query(g_pts, k=2, workers=-1)[0][:, 1]))
                gate, gate_rule = opts.gate_factor * spacing, f"{opts.gate_factor} x GT spacing {spacing:.4g}"
            near_p, near_g = d_p < gate, d_g < gate
            if not near_p.any() or not near_g.any():
                raise EvaluationError(
                    f"normal_similarity: no NN pair of {geo.label} and {path} is closer than {gate:.4g}; "
                    f"wrong frame or units (fix: check frame= and the scene normalisation)"
                )
        acc, comp = float(cos_p[near_p].mean()), float(cos_g[near_g].mean())
        diag.data.update(max_dist=gate, max_dist_rule=gate_rule, accuracy_pairs_fraction=float(near_p.mean()),
                         completeness_pairs_fraction=float(near_g.mean()))
        return {
            "metrics": {
                "normal_consistency": (acc + comp) / 2,
                "normal_accuracy": acc,
                "normal_completeness": comp,
                "normal_consistency_ungated": float((cos_p.mean() + cos_g.mean()) / 2),
            },
            "protocol": self.protocol(opts) | {"max_dist": gate},
            "diagnostics": diag.finish(),
        }
