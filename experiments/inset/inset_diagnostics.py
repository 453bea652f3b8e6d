"""Where a finished run's inset lives: primitive centres and thickness, and the offset against curvature.

Two diagnostics of a run folder (``runs/<dataset>/<scene>/<method>/<id>``) on a built-in synthetic
scene, in pixel footprints of the run's resolution (`gsbench.evaluators.surface_offset`):

- ``primitives``: the signed distance of every Gaussian centre to the exact surface (those within
  5 px), its median and opacity-weighted mean, and the median smallest / largest scale in px (the
  smallest is 0 for 2D surfels). If the inset were the primitives' own thickness, the centres would
  sit about one smallest scale inside.
- ``curvature``: the signed offset of 40 000 mesh samples binned by the mean curvature κ of the exact
  surface at their closest point, estimated from exact-surface samples within 3 px by the paraboloid
  fit ``κ = −2 Σ h / Σ t²`` (h: height above the tangent plane, t: tangential distance; κ > 0
  convex). Flat discs tangent to a convex surface stick out by the sagitta a²κ/2, so an inset made
  by that would grow with κ.

Usage: ``python experiments/inset/inset_diagnostics.py primitives|curvature RUN_FOLDER``
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch
import trimesh
import yaml
from scipy.spatial import cKDTree

from gsbench.config.run_config import completed_config
from gsbench.data.loader import load_scene
from gsbench.data.synthetic.make import ensure_scene
from gsbench.evaluators import pointsets
from gsbench.evaluators.surface_offset import gt_mesh_file, pixel_footprint, signed_distances
from gsbench.run_folder import RunFolder
from gsbench.training.trainer import load_checkpoint

GATE_PX = 5.0
CURVATURE_RADIUS_PX = 3.0
MESH_SAMPLES, CURVATURE_POINTS, EXACT_SAMPLES = 40_000, 6_000, 300_000


def _run_scene(run: Path):
    cfg = completed_config(yaml.safe_load((run / "config.yaml").read_text()))
    ensure_scene(cfg["scene"])
    scene = load_scene(cfg["scene"], downscale=cfg["data"]["downscale"], max_size=cfg["data"].get("max_size", ()),
                       load_images=False, tnt_frame=cfg["data"]["tnt_frame"])
    gt = trimesh.load(gt_mesh_file(scene), process=False)
    return scene, gt, pixel_footprint(scene, (gt.bounds[0] + gt.bounds[1]) / 2)


def primitives(run: Path) -> None:
    scene, gt, fp = _run_scene(run)
    p = load_checkpoint(RunFolder(run).final_checkpoint)["method"]["params"]
    means = scene.normalisation.apply(p["means"].double().numpy())
    scales = torch.exp(p["log_scales"].double()).numpy() * scene.normalisation.scale / fp
    opacity = torch.sigmoid(p["opacity_logits"].double()).numpy().reshape(-1)
    s = signed_distances(means, np.asarray(gt.vertices), np.asarray(gt.faces)) / fp
    near = np.abs(s) < GATE_PX
    smallest = scales.min(axis=1) if scales.shape[1] == 3 else np.zeros(len(scales))
    print(f"{run}: {len(s)} primitives, {near.sum()} within {GATE_PX} px of the surface; centre offset median "
          f"{np.median(s[near]):+.2f} px, opacity-weighted mean {np.average(s[near], weights=opacity[near]):+.2f} px; "
          f"smallest scale median {np.median(smallest[near]):.2f} px, largest {np.median(scales.max(axis=1)[near]):.2f} px "
          f"(footprint {fp:.4g})")


def curvature(run: Path) -> None:
    scene, gt, fp = _run_scene(run)
    mesh = trimesh.load(run / "mesh.ply", process=False)
    samples, _ = pointsets.sample_surface(scene.normalisation.apply(np.asarray(mesh.vertices)), np.asarray(mesh.faces),
                                          MESH_SAMPLES, 0)
    s = signed_distances(samples, np.asarray(gt.vertices), np.asarray(gt.faces)) / fp
    keep = np.flatnonzero(np.abs(s) < GATE_PX)
    keep = np.random.default_rng(0).choice(keep, min(CURVATURE_POINTS, len(keep)), replace=False)
    exact, normals = pointsets.sample_surface(np.asarray(gt.vertices), np.asarray(gt.faces), EXACT_SAMPLES, 1)
    tree = cKDTree(exact)
    _, nearest = tree.query(samples[keep])  # the exact sample nearest to each mesh sample
    kappa = np.empty(len(keep))
    for k, nb in enumerate(tree.query_ball_point(exact[nearest], CURVATURE_RADIUS_PX * fp)):
        d = exact[nb] - exact[nearest[k]]
        h = d @ normals[nearest[k]]
        kappa[k] = -2.0 * h.sum() / max(((d * d).sum(axis=1) - h * h).sum(), 1e-30)
    edges = np.quantile(kappa, [0.0, 0.1, 0.3, 0.5, 0.7, 0.9, 1.0])
    print(f"{run}: signed offset (px) by mean curvature of the exact surface (footprint {fp:.4g})")
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (kappa >= lo) & (kappa <= hi)
        print(f"  kappa in [{lo:+.4f}, {hi:+.4f}] per unit: median offset {np.median(s[keep][sel]):+.2f} px ({sel.sum()})")


if __name__ == "__main__":
    if len(sys.argv) != 3 or sys.argv[1] not in ("primitives", "curvature"):
        sys.exit(__doc__)
    {"primitives": primitives, "curvature": curvature}[sys.argv[1]](Path(sys.argv[2]))
