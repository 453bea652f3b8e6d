"""DTU Chamfer distance, reproducing DTUeval-python ``eval.py`` after mask culling (`gsbench.evaluators.culling`),
protocol v1, as docs/evaluation.md §2.2 states it: the mesh's vertices plus a per-triangle barycentric grid,
seeded shuffle and greedy 0.2 mm downsampling, box and ObsMask filters; accuracy and completeness the mean NN
distances below ``max_dist`` (larger ones dropped, not clipped); chamfer = (accuracy + completeness) / 2, in mm.

Beside it, the same steps on area samples of the mesh (``*_sampled``, docs/evaluation.md §2.4): the official
first step depends on the triangulation, the samples only on the surface. The reference's shuffle is
unseeded, so ``seed`` is a protocol parameter here.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from gsbench.data.camera import Scene
from gsbench.data.dtu import dtu_gt_paths
from gsbench.errors import EvaluationError
from gsbench.evaluators import culling, gt_io, pointsets
from gsbench.evaluators.base import Diagnostics, Evaluator, MetricInfo, check_files, require_gt
from gsbench.evaluators.dtu_gt import DTUGroundTruth
from gsbench.evaluators.geometry import load_geometry, to_dataset_frame, to_normalised_frame
from gsbench.resources import available_memory_bytes, memory_size


SAMPLE_BYTES = 48 + pointsets.DOWNSAMPLE_BYTES["point"]  # a sample: its row, its copy beside the vertices, and its
# share of the downsampling before any pair (its pairs are checked once the points exist)


@dataclass(frozen=True)
class DTUOptions:
    """Protocol parameters (defaults = DTUeval-python CLI defaults + 2DGS culling)."""

    mode: str = "mesh"  # "mesh" | "pcd"
    cull: str = "2dgs"  # culling.CULL_CONVENTIONS ("2dgs", "gof") or "none"
    downsample_density: float = 0.2  # mm
    patch_size: float = 60  # mm; the box is [BB0 - patch, BB1 + 2 patch)
    max_dist: float = 20  # mm; distances >= max_dist are dropped
    seed: int = 0  # shuffle before greedy downsampling (and the area samples)
    frame: str = "normalised"  # or "dataset": the mesh is already in DTU world (mm)
    visualize_threshold: float = 10  # mm, colour scale of the vis plys
    vis_dir: str | None = None  # write vis_{scan}_d2s.ply / _s2d.ply here
    min_inside_fraction: float = 0.1  # warn (units/frame) when fewer vertices lie in the GT box
    max_sample_points: int | None = None  # refuse meshes sampling more points; None: what memory holds (sample_limit)
    sample_oversample: float = 4.0  # area samples per downsample_density² of surface (sampled protocol)
    sampled: bool = True  # mode "mesh": also score area samples (*_sampled); False: the official steps only


def dtu_gt_files(scene: Scene) -> dict[str, Path]:
    """The three DTUeval-python inputs for the scene's scan (docs/evaluation.md §2.1)."""
    gt = require_gt(scene, "dtu", DTUChamfer.name)
    if gt.scan is None:
        raise EvaluationError(f"dtu_chamfer: scene '{scene.name}' GroundTruth has no scan number")
    return dtu_gt_paths(gt.root, gt.scan)


def _distance_colors(dist: np.ndarray, valid: np.ndarray, max_dist: float, vis_thr: float) -> np.ndarray:
    colors = np.tile([0.0, 0.0, 1.0], (len(valid), 1))
    alpha = (np.minimum(dist, vis_thr) / vis_thr)[:, None]
    colors[valid] = alpha * np.array([1.0, 0.0, 0.0]) + (1 - alpha) * np.ones(3)
    far = np.flatnonzero(valid)[dist >= max_dist]
    colors[far] = [0.0, 1.0, 0.0]
    return colors


def _mean_below(dist: np.ndarray, max_dist: float, what: str, label: str) -> tuple[float, float]:
    near = dist < max_dist
    if not near.any():
        raise EvaluationError(
            f"dtu_chamfer: no {what} distance is below max_dist={max_dist} mm for {label}; "
            f"the mesh is probably in the wrong frame or units (fix: check frame= and the scene normalisation)"
        )
    return float(dist[near].mean()), float(1 - near.mean())


@dataclass
class _Scored:
    """Steps 2-7 on one point set: the metrics and what the visualisation and diagnostics need."""

    accuracy: float
    completeness: float
    data: np.ndarray
    valid: np.ndarray
    d2s: np.ndarray
    s2d: np.ndarray
    counts: dict


def sample_limit(limit: int | None, available: int | None = None) -> int | None:
    """``limit`` if given, else the samples the memory available holds (`gsbench.resources.available_memory_bytes`
    unless given) at `SAMPLE_BYTES` each; None where that is not known. A mesh's samples are bounded by its
    area, and a method's mesh may be far larger than the object (a Poisson surface closed around the
    background); only memory stops it, and `check_downsample_memory` then checks the downsampling's pairs."""
    if limit is not None:
        return limit
    available = available_memory_bytes() if available is None else available
    return None if available is None else available // SAMPLE_BYTES


def check_sample_counts(verts: np.ndarray, faces: np.ndarray, opts: DTUOptions, limit: int | None) -> None:
    """Both point sets of mode ``mesh`` (the official grid samples and, if ``opts.sampled``, the area samples)
    checked against ``limit`` (`sample_limit`) before any work, so a mesh too large for either fails in seconds."""
    bound = pointsets.barycentric_grid_bound(verts, faces, opts.downsample_density)
    area = float(pointsets.face_normals(verts, faces)[1].sum())
    pointsets.check_sample_count(bound, f"samples at density {opts.downsample_density}", limit, area)
    if opts.sampled:
        pointsets.check_sample_count(
            pointsets.area_sample_count(area, opts.downsample_density, opts.sample_oversample),
            f"area samples at spacing {opts.downsample_density:.4g}", limit, area)


def check_downsample_memory(data: np.ndarray, density: float, label: str, available: int | None = None) -> None:
    """EvaluationError when the greedy downsampling of ``data`` at ``density`` needs more than the memory available:
    it holds every pair of points closer than ``density`` (`pointsets.radius_pair_estimate`,
    `pointsets.greedy_downsample_memory`), as many as the square of a mesh's vertices on a given surface."""
    available = available_memory_bytes() if available is None else available
    if available is None:
        return
    pairs = pointsets.radius_pair_estimate(data, density)
    need = pointsets.greedy_downsample_memory(len(data), pairs)
    if need > available:
        raise EvaluationError(
            f"dtu_chamfer: downsampling the {len(data):,} points of {label} at {density} mm holds every pair closer "
            f"than that, about {pairs:,}: {memory_size(need)} in all, but {memory_size(available)} is available; fix: "
            f"decimate the mesh (vertices {density} mm apart lose nothing this protocol sees), or run it on a larger "
            "machine")


def _score(data: np.ndarray, gt: DTUGroundTruth, stl_trees, opts: DTUOptions, label: str, where: str,
           diag: Diagnostics, prefix: str = "") -> _Scored:
    """Steps 2-7 for the points ``data`` (mm), each timed as ``{prefix}{step}``, the downsampling's memory
    checked first (`check_downsample_memory`); ``stl_trees`` caches the STL KD-tree between point sets."""
    with diag.phase(f"{prefix}downsample"):
        check_downsample_memory(data, opts.downsample_density, label)
        data = pointsets.greedy_downsample(data, opts.downsample_density, opts.seed)
    with diag.phase(f"{prefix}mask"):
        inbound = gt.in_box(data, opts.patch_size)
        data_in = data[inbound]
        in_obs = gt.observed(data_in)
        data_in_obs = data_in[in_obs]
    if len(data_in_obs) == 0:
        raise EvaluationError(
            f"dtu_chamfer: no point of {label} lies inside the observation mask {where}; "
            f"wrong frame or units (fix: check frame= and the scene normalisation)"
        )
    with diag.phase(f"{prefix}accuracy"):
        if "stl" not in stl_trees:
            stl_trees["stl"] = cKDTree(gt.stl)
        d2s = pointsets.nn_distances(data_in_obs, stl_trees["stl"], opts.max_dist, desc="accuracy")
        acc, acc_drop = _mean_below(d2s, opts.max_dist, "accuracy", label)
    with diag.phase(f"{prefix}completeness"):
        s2d = pointsets.nn_distances(gt.completeness_points(), cKDTree(data_in), opts.max_dist, desc="completeness")
        comp, comp_drop = _mean_below(s2d, opts.max_dist, "completeness", label)
    valid = np.zeros(len(data), bool)
    valid[np.flatnonzero(inbound)[in_obs]] = True
    counts = {"downsampled_points": len(data), "in_box_points": len(data_in), "in_obs_points": len(data_in_obs),
              "in_box_fraction": float(inbound.mean()), "accuracy_dropped_fraction": acc_drop,
              "completeness_dropped_fraction": comp_drop}
    return _Scored(acc, comp, data, valid, d2s, s2d, counts)


class DTUChamfer(Evaluator):
    """Accuracy, completeness and their mean (mm), exactly as DTUeval-python computes them, and the same on
    area samples of the mesh."""

    name = "dtu_chamfer"
    version = 1
    memory_per_face = 360
    requires = ("mesh",)
    metrics = {
        "accuracy": MetricInfo(False, "mm", "mean distance reconstruction -> GT (d2s), inside ObsMask"),
        "completeness": MetricInfo(False, "mm", "mean distance GT (above the plane) -> reconstruction (s2d)"),
        "chamfer": MetricInfo(False, "mm", "(accuracy + completeness) / 2"),
        "accuracy_sampled": MetricInfo(False, "mm", "accuracy of area samples of the mesh (tessellation-independent)"),
        "completeness_sampled": MetricInfo(False, "mm", "completeness of area samples of the mesh"),
        "chamfer_sampled": MetricInfo(False, "mm", "(accuracy_sampled + completeness_sampled) / 2"),
    }
    Options = DTUOptions

    def validate(self, scene: Scene) -> None:
        check_files(self.name, dtu_gt_files(scene),
                    "download the DTU evaluation data (Points/stl and ObsMask from the DTU MVS SampleSet) "
                    "and pass --gt PATH, the folder holding Points/ and ObsMask/")

    def evaluate(self, mesh, scene: Scene, **options) -> dict:
        opts = self.options(**options)
        if opts.mode not in ("mesh", "pcd"):
            raise EvaluationError(f"dtu_chamfer: mode must be 'mesh' or 'pcd', got '{opts.mode}'")
        culling.check_cull(opts.cull)
        self.validate(scene)
        files = dtu_gt_files(scene)
        diag = Diagnostics()
        diag["threads"] = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()

        with diag.phase("load"):
            geo = load_geometry(mesh, need_faces=opts.mode == "mesh")
            verts, faces = geo.vertices, geo.faces if opts.mode == "mesh" else None
            diag["input_vertices"], diag["input_faces"] = len(verts), 0 if faces is None else len(faces)
        with diag.phase("cull"):
            keep, faces = culling.cull_mesh(to_normalised_frame(verts, scene, opts.frame), faces, scene, opts.cull,
                                            f"dtu_chamfer: {geo.label}", opts.frame)
            diag["culled_vertices"] = int((~keep).sum())
        verts = to_dataset_frame(verts[keep], scene, opts.frame)

        with diag.phase("load_gt"):
            gt = DTUGroundTruth.read(files)
            diag["stl_points"] = len(gt.stl)
            frac = float(gt.in_box(verts, opts.patch_size).mean())
            diag["vertices_in_box_fraction"] = frac
            if frac < opts.min_inside_fraction:
                diag.warn(
                    f"dtu_chamfer: only {100 * frac:.1f}% of the vertices of {geo.label} lie inside the GT bounding "
                    f"box (expected most): wrong units or frame? (frame='{opts.frame}', scale to GT "
                    f"{scene.normalisation.scale})"
                )

        limit = sample_limit(opts.max_sample_points)  # read once: the memory available moves during a run
        if opts.mode == "mesh":
            check_sample_counts(verts, faces, opts, limit)
        with diag.phase("sample"):
            if opts.mode == "mesh":
                samples = pointsets.barycentric_grid_samples(verts, faces, opts.downsample_density,
                                                             limit)
                data = np.concatenate([verts, samples], axis=0)
            else:
                data = verts
            diag["sampled_points"] = len(data)
        trees: dict = {}
        official = _score(data, gt, trees, opts, geo.label, str(files["ObsMask"]), diag)
        diag.data.update(official.counts, stl_above_plane=len(official.s2d))
        metrics = {"accuracy": official.accuracy, "completeness": official.completeness,
                   "chamfer": (official.accuracy + official.completeness) / 2}
        if opts.mode == "mesh" and opts.sampled:
            with diag.phase("sampled_draw"):
                area = pointsets.area_samples(verts, faces, opts.downsample_density, opts.seed, opts.sample_oversample,
                                              limit)
            if len(area) == 0:
                raise EvaluationError(f"dtu_chamfer: {geo.label} has no surface area left after culling")
            sampled = _score(area, gt, trees, opts, geo.label, str(files["ObsMask"]), diag, "sampled_")
            diag["area_samples"] = {"drawn": len(area), **sampled.counts}
            metrics |= {"accuracy_sampled": sampled.accuracy, "completeness_sampled": sampled.completeness,
                        "chamfer_sampled": (sampled.accuracy + sampled.completeness) / 2}

        if opts.vis_dir is not None:
            with diag.phase("visualise"):
                scan, out = scene.gt.scan, Path(opts.vis_dir)
                gt_io.write_colored_ply(out / f"vis_{scan:03d}_d2s.ply", official.data,
                                        _distance_colors(official.d2s, official.valid, opts.max_dist,
                                                         opts.visualize_threshold))
                gt_io.write_colored_ply(out / f"vis_{scan:03d}_s2d.ply", gt.stl,
                                        _distance_colors(official.s2d, gt.above_plane(gt.stl), opts.max_dist,
                                                         opts.visualize_threshold))
                diag["vis_files"] = [str(out / f"vis_{scan:03d}_{k}.ply") for k in ("d2s", "s2d")]

        return {"metrics": metrics, "protocol": self.protocol(opts), "diagnostics": diag.finish()}
