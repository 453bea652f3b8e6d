"""Normal consistency of a mesh against ground truth (Occupancy Networks ``im2mesh/eval.py``), protocol v2, as
docs/evaluation.md §4.1, §4.2 state it, on exactly the points the dataset's geometry protocol scores.

``normal_consistency = (acc_n + comp_n) / 2``, ``acc_n = mean_p |n_p·n_gt(NN_gt(p))|`` over the mesh's samples and
``comp_n = mean_g |n_g·n_pred(NN_pred(g))|`` over the GT's, over every pair (a hole or a floater lowers it); the
``*_gated`` variants keep the pairs closer than ``max_dist``. Protocol v1 (before 2026-11-24) headlined the gated
mean on the unfiltered STL points; its numbers are not comparable. Image-space normals:
`rendered_normal_similarity` (docs/evaluation.md §4.3).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from gsbench.data.camera import Scene
from gsbench.data.dtu import dtu_gt_paths
from gsbench.errors import EvaluationError, import_open3d
from gsbench.evaluators import culling, gt_io, pointsets
from gsbench.evaluators.base import Diagnostics, Evaluator, MetricInfo, check_files
from gsbench.evaluators.dtu_gt import DTUGroundTruth
from gsbench.evaluators.geometry import load_geometry, to_dataset_frame, to_normalised_frame
from gsbench.signals import signals_deferred


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
    cull: str = "2dgs"  # dtu scenes: the mask culling of dtu_chamfer (2dgs, gof or none)
    patch_size: float = 60  # dtu scenes: the box of dtu_chamfer, BB[0] - patch <= p < BB[1] + 2 patch (mm)


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
        return dtu_gt_paths(root, scene.gt.scan)["STL points"]
    return root / f"{scene.gt.name}.ply"


def _gt_samples(path: Path, as_mesh: bool | None, opts: NormalOptions, keep=None) -> tuple[np.ndarray, np.ndarray, str]:
    """(points, unit normals, how) for the GT; ``as_mesh=None`` decides by whether the file has faces;
    ``keep(points) -> bool mask`` restricts a point file's samples (PCA normals still use every point)."""
    if as_mesh is not False:
        geo = load_geometry(path)
        if geo.is_mesh:
            pts, nrm = pointsets.sample_surface(geo.vertices, geo.faces, opts.n_samples, opts.seed + 1)
            return pts, nrm, "mesh samples"
        if as_mesh:
            raise EvaluationError(f"normal_similarity: gt_mesh {path} has no faces (fix: pass it as gt_points=)")
    pts, normals = gt_io.read_points(path, with_normals=True)
    allowed = np.flatnonzero(keep(pts)) if keep is not None else np.arange(len(pts))
    if len(allowed) == 0:
        raise EvaluationError(f"normal_similarity: no point of {path} is scored by the protocol (all filtered out)")
    rng = np.random.default_rng(opts.seed + 1)
    sub = np.sort(rng.choice(allowed, opts.n_samples, replace=False)) if len(allowed) > opts.n_samples else allowed
    if normals is not None and np.isfinite(normals[sub]).all() and (np.linalg.norm(normals[sub], axis=1) > 0).all():
        return pts[sub], normals[sub] / np.linalg.norm(normals[sub], axis=1, keepdims=True), "file normals"
    return pts[sub], pointsets.pca_normals(pts, pts[sub], opts.k_pca), f"PCA normals (k={opts.k_pca})"


def _abs_cos(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(np.einsum("ij,ij->i", a, b))


def rendered_normal_similarity(pred_normals: np.ndarray, gt_normals: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean cosine ``n_pred . n_gt`` over ``mask`` for HxWx3 normal maps (docs/evaluation.md §4.3).

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


def _protocol_filters(scene: Scene, opts: NormalOptions):
    """(prediction filter, GT filter) for the scene's kind (module docstring): functions of points in the
    GT frame returning a bool mask, or None for no filter."""
    root = Path(scene.gt.root)
    if scene.gt.kind == "dtu":
        gt = DTUGroundTruth.read(dtu_gt_paths(root, scene.gt.scan))
        return (lambda p: gt.in_box(p, opts.patch_size) & gt.observed(p)), gt.above_plane
    if scene.gt.kind == "tnt":
        volume = gt_io.read_crop_volume(root / f"{scene.gt.name}.json")
        return (lambda p: crop_mask(volume, p)), (lambda p: crop_mask(volume, p))
    return None, None


def crop_mask(volume, points: np.ndarray) -> np.ndarray:
    """Per point: inside a TnT crop volume (open3d ``SelectionPolygonVolume``)."""
    o3d = import_open3d()
    if len(points) == 0:
        return np.zeros(0, bool)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    inside = np.zeros(len(points), bool)
    inside[np.asarray(volume.crop_in_polygon(cloud), np.int64)] = True
    return inside


class NormalSimilarity(Evaluator):
    """Normal consistency NC in [0, 1] between mesh and GT surface normals, ungated (headline) and gated."""

    name = "normal_similarity"
    version = 2
    memory_per_face = 310
    requires = ("mesh",)
    metrics = {
        "normal_consistency": MetricInfo(True, "", "mean |cos| of NN normal pairs, both ways (every pair)"),
        "normal_accuracy": MetricInfo(True, "", "mean |cos|, prediction -> GT"),
        "normal_completeness": MetricInfo(True, "", "mean |cos|, GT -> prediction"),
        "normal_consistency_gated": MetricInfo(True, "", "NC over the NN pairs closer than max_dist"),
        "normal_accuracy_gated": MetricInfo(True, "", "gated mean |cos|, prediction -> GT"),
        "normal_completeness_gated": MetricInfo(True, "", "gated mean |cos|, GT -> prediction"),
    }
    Options = NormalOptions

    def validate(self, scene: Scene) -> None:
        check_files(self.name, {"GT surface": gt_surface_file(scene)},
                    "provide the scene's ground-truth points or mesh (--gt PATH), or the gt_mesh/gt_points options")

    def evaluate(self, mesh, scene: Scene, **options) -> dict:
        opts = self.options(**options)
        culling.check_cull(opts.cull)
        diag = Diagnostics()
        keep_pred = keep_gt = None
        with diag.phase("load"):
            geo = load_geometry(mesh, need_faces=True)
            verts, faces = geo.vertices, geo.faces
            if opts.gt_mesh or opts.gt_points:
                path, as_mesh = Path(opts.gt_mesh or opts.gt_points), bool(opts.gt_mesh)
                if not path.is_file():
                    raise EvaluationError(f"normal_similarity: GT file not found: {path}")
                verts = to_dataset_frame(verts, scene, opts.frame)
            else:
                self.validate(scene)
                path, as_mesh = gt_surface_file(scene), (False if scene.gt.kind in ("dtu", "tnt") else None)
                if scene.gt.kind == "dtu":
                    keep, faces = culling.cull_mesh(to_normalised_frame(verts, scene, opts.frame), faces, scene,
                                                    opts.cull, f"normal_similarity: {geo.label}", opts.frame)
                    verts = verts[keep]
                verts = to_dataset_frame(verts, scene, opts.frame)
                if scene.gt.kind == "tnt":
                    trans = gt_io.read_matrix4(Path(scene.gt.root) / f"{scene.gt.name}_trans.txt")
                    verts = verts @ trans[:3, :3].T + trans[:3, 3]
                keep_pred, keep_gt = _protocol_filters(scene, opts)
        with diag.phase("sample"):
            try:
                p_pts, p_nrm = pointsets.sample_surface(verts, faces, opts.n_samples, opts.seed)
            except ValueError as exc:
                raise EvaluationError(f"normal_similarity: {geo.label}: {exc}") from exc
            if keep_pred is not None:
                kept = keep_pred(p_pts)
                if not kept.any():
                    raise EvaluationError(f"normal_similarity: no sample of {geo.label} lies where the protocol scores "
                                          f"(ObsMask / crop); wrong frame or units (fix: check frame=)")
                p_pts, p_nrm = p_pts[kept], p_nrm[kept]
            g_pts, g_nrm, how = _gt_samples(path, as_mesh, opts, keep_gt)
            diag.data.update(gt_file=str(path), gt_normals=how, pred_samples=len(p_pts), gt_samples=len(g_pts),
                             filtered=keep_pred is not None)
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
                with signals_deferred():
                    spacing = float(np.median(g_tree.query(g_pts, k=2, workers=-1)[0][:, 1]))
                gate, gate_rule = opts.gate_factor * spacing, f"{opts.gate_factor} x GT spacing {spacing:.4g}"
            near_p, near_g = d_p < gate, d_g < gate
            gated = near_p.any() and near_g.any()
            if not gated and keep_pred is None:
                raise EvaluationError(
                    f"normal_similarity: no NN pair of {geo.label} and {path} is closer than {gate:.4g}; "
                    f"wrong frame or units, or a mesh nowhere near the GT (fix: check frame= and the scene "
                    f"normalisation)"
                )
        acc, comp = float(cos_p.mean()), float(cos_g.mean())
        metrics = {"normal_consistency": (acc + comp) / 2, "normal_accuracy": acc, "normal_completeness": comp}
        if gated:
            acc_gated, comp_gated = float(cos_p[near_p].mean()), float(cos_g[near_g].mean())
            metrics |= {"normal_consistency_gated": (acc_gated + comp_gated) / 2, "normal_accuracy_gated": acc_gated,
                        "normal_completeness_gated": comp_gated}
        else:  # the protocol's filter kept samples, so the frame is right: the mesh itself is far from the GT
            diag.warn(f"normal_similarity: no NN pair of {geo.label} and the GT is closer than max_dist {gate:.4g} "
                      f"(nearest {float(d_p.min()):.4g}); the *_gated metrics are undefined and left out")
        diag.data.update(max_dist=gate, max_dist_rule=gate_rule, accuracy_pairs_fraction=float(near_p.mean()),
                         completeness_pairs_fraction=float(near_g.mean()))
        return {
            "metrics": metrics,
            "protocol": self.protocol(opts) | {"max_dist": gate},
            "diagnostics": diag.finish(),
        }
