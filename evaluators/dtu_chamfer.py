"""DTU Chamfer distance, reproducing DTUeval-python ``eval.py`` (evaluation.md §1.2), protocol v1.

Optionally preceded by the 2DGS mask culling (evaluation.md §1.3, `gsbench.evaluators.culling`).

Steps (numbers as in evaluation.md §1.2):

1. mesh -> points: the vertices plus the per-triangle barycentric grid at ``downsample_density``
   (`pointsets.barycentric_grid_samples`); ``mode="pcd"`` uses the points as given.
2-3. seeded shuffle and greedy 0.2 mm downsampling (`pointsets.greedy_downsample`); the reference
   shuffle is unseeded, so ``seed`` is a protocol parameter here.
4. box ``BB[0] - patch_size <= p < BB[1] + 2 * patch_size`` (asymmetric, as coded in the reference);
   grid cell ``g = round((p - BB[0]) / Res)`` (half to even, like ``np.around``), cells outside the
   ObsMask array are dropped, ``ObsMask[g]`` selects the accuracy points.
5. accuracy: mean NN distance from ObsMask points to the STL points over distances ``< max_dist``
   (larger ones are dropped, not clipped).
6. completeness: STL points with ``[x y z 1] . P > 0`` (Plane.mat), NN distance to the **box-filtered**
   (not ObsMask-filtered) points, mean over ``< max_dist``.
7. overall = (accuracy + completeness) / 2, all in mm.
8. optional visualisations ``vis_{scan:03d}_d2s.ply`` / ``_s2d.ply``: blue = outside box/mask (or below
   the plane), green = ``>= max_dist``, white -> red over ``[0, visualize_threshold]``.
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
from gsbench.evaluators.geometry import load_geometry, to_dataset_frame, to_normalised_frame


@dataclass(frozen=True)
class DTUOptions:
    """Protocol parameters (defaults = DTUeval-python CLI defaults + 2DGS culling)."""

    mode: str = "mesh"  # "mesh" | "pcd"
    cull: bool = True  # 2DGS mask culling before evaluation
    dilation: float = 24  # disk radius in px at reference_width
    reference_width: int = 1600
    downsample_density: float = 0.2  # mm
    patch_size: float = 60  # mm; the box is [BB0 - patch, BB1 + 2 patch)
    max_dist: float = 20  # mm; distances >= max_dist are dropped
    seed: int = 0  # shuffle before greedy downsampling
    frame: str = "normalised"  # or "dataset": the mesh is already in DTU world (mm)
    visualize_threshold: float = 10  # mm, colour scale of the vis plys
    vis_dir: str | None = None  # write vis_{scan}_d2s.ply / _s2d.ply here
    min_inside_fraction: float = 0.1  # warn (units/frame) when fewer vertices lie in the GT box
    max_sample_points: int = 50_000_000  # refuse meshes whose sampling would exceed this (memory guard)


def dtu_gt_files(scene: Scene) -> dict[str, Path]:
    """The three DTUeval-python inputs for the scene's scan (evaluation.md §1.1)."""
    gt = require_gt(scene, "dtu", DTUChamfer.name)
    if gt.scan is None:
        raise EvaluationError(f"dtu_chamfer: scene '{scene.name}' GroundTruth has no scan number")
    return dtu_gt_paths(gt.root, gt.scan)


def _in_box(points: np.ndarray, bb: np.ndarray, patch: float) -> np.ndarray:
    """Step 4 box: ``BB[0] - patch <= p < BB[1] + 2 patch`` on every axis."""
    return np.all(points >= bb[0] - patch, axis=1) & np.all(points < bb[1] + 2 * patch, axis=1)


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


class DTUChamfer(Evaluator):
    """Accuracy, completeness and their mean (mm), exactly as DTUeval-python computes them."""

    name = "dtu_chamfer"
    version = 1
    requires = ("mesh",)
    metrics = {
        "accuracy": MetricInfo(False, "mm", "mean distance reconstruction -> GT (d2s), inside ObsMask"),
        "completeness": MetricInfo(False, "mm", "mean distance GT (above the plane) -> reconstruction (s2d)"),
        "chamfer": MetricInfo(False, "mm", "(accuracy + completeness) / 2"),
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
        self.validate(scene)
        files = dtu_gt_files(scene)
        diag = Diagnostics()
        diag["threads"] = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()

        with diag.phase("load"):
            geo = load_geometry(mesh, need_faces=opts.mode == "mesh")
            verts, faces = geo.vertices, geo.faces if opts.mode == "mesh" else None
            diag["input_vertices"], diag["input_faces"] = len(verts), 0 if faces is None else len(faces)
        if opts.cull:
            with diag.phase("cull"):
                keep = culling.cull_vertices(to_normalised_frame(verts, scene, opts.frame), scene,
                                             opts.dilation, opts.reference_width)
                if not keep.any():
                    raise EvaluationError(
                        f"dtu_chamfer: culling removed every vertex of {geo.label}: no vertex projects onto "
                        f"the masks (fix: check frame= — '{opts.frame}' — and the scene cameras)"
                    )
                faces = None if faces is None else culling.kept_faces(faces, keep)
                verts = verts[keep]
                diag["culled_vertices"] = int((~keep).sum())
        verts = to_dataset_frame(verts, scene, opts.frame)

        with diag.phase("load_gt"):
            obs = gt_io.read_mat(files["ObsMask"], ("ObsMask", "BB", "Res"))
            plane = gt_io.read_mat(files["Plane"], ("P",))["P"].reshape(4).astype(np.float64)
            stl = gt_io.read_points(files["STL points"])
            mask, bb, res = obs["ObsMask"].astype(bool), obs["BB"].astype(np.float64), float(np.ravel(obs["Res"])[0])
            diag["stl_points"] = len(stl)
            frac = float(_in_box(verts, bb, opts.patch_size).mean())
            diag["vertices_in_box_fraction"] = frac
            if frac < opts.min_inside_fraction:
                diag.warn(
                    f"dtu_chamfer: only {100 * frac:.1f}% of the vertices of {geo.label} lie inside the GT bounding "
                    f"box (expected most): wrong units or frame? (frame='{opts.frame}', scale to GT "
                    f"{scene.normalisation.scale})"
                )

        with diag.phase("sample"):
            if opts.mode == "mesh":
                samples = pointsets.barycentric_grid_samples(verts, faces, opts.downsample_density,
                                                             opts.max_sample_points)
                data = np.concatenate([verts, samples], axis=0)
            else:
                data = verts
            diag["sampled_points"] = len(data)
        with diag.phase("downsample"):
            data = pointsets.greedy_downsample(data, opts.downsample_density, opts.seed)
            diag["downsampled_points"] = len(data)

        with diag.phase("mask"):
            inbound = _in_box(data, bb, opts.patch_size)
            data_in = data[inbound]
            grid = np.around((data_in - bb[0]) / res).astype(np.int32)
            in_grid = np.all((grid >= 0) & (grid < np.array(mask.shape)), axis=1)
            in_obs = np.zeros(len(data_in), bool)
            g = grid[in_grid]
            in_obs[in_grid] = mask[g[:, 0], g[:, 1], g[:, 2]]
            data_in_obs = data_in[in_obs]
            diag.data.update(in_box_points=len(data_in), in_obs_points=len(data_in_obs),
                             in_box_fraction=float(inbound.mean()))
            if len(data_in_obs) == 0:
                raise EvaluationError(
                    f"dtu_chamfer: no point of {geo.label} lies inside the observation mask {files['ObsMask']}; "
                    f"wrong frame or units (fix: check frame= and the scene normalisation)"
                )

        with diag.phase("accuracy"):
            d2s = pointsets.nn_distances(data_in_obs, cKDTree(stl), opts.max_dist, desc="accuracy")
            acc, acc_drop = _mean_below(d2s, opts.max_dist, "accuracy", geo.label)
        with diag.phase("completeness"):
            above = stl[:, 0] * plane[0] + stl[:, 1] * plane[1] + stl[:, 2] * plane[2] + plane[3] > 0  # [x y z 1].P
            stl_above = stl[above]
            s2d = pointsets.nn_distances(stl_above, cKDTree(data_in), opts.max_dist, desc="completeness")
            comp, comp_drop = _mean_below(s2d, opts.max_dist, "completeness", geo.label)
            diag.data.update(stl_above_plane=len(stl_above), accuracy_dropped_fraction=acc_drop,
                             completeness_dropped_fraction=comp_drop)

        if opts.vis_dir is not None:
            with diag.phase("visualise"):
                scan, out = scene.gt.scan, Path(opts.vis_dir)
                valid = np.zeros(len(data), bool)
                valid[np.flatnonzero(inbound)[in_obs]] = True
                gt_io.write_colored_ply(out / f"vis_{scan:03d}_d2s.ply", data,
                                        _distance_colors(d2s, valid, opts.max_dist, opts.visualize_threshold))
                gt_io.write_colored_ply(out / f"vis_{scan:03d}_s2d.ply", stl,
                                        _distance_colors(s2d, above, opts.max_dist, opts.visualize_threshold))
                diag["vis_files"] = [str(out / f"vis_{scan:03d}_{k}.ply") for k in ("d2s", "s2d")]

        return {
            "metrics": {"accuracy": acc, "completeness": comp, "chamfer": (acc + comp) / 2},
            "protocol": self.protocol(opts),
            "diagnostics": diag.finish(),
        }
