"""`gsbench depth`: a trained run's depth against the exact depth of its synthetic scene, view by view.

For a run folder (``config.yaml`` and ``checkpoint-final.pt``) on a built-in synthetic scene, the depth the
TSDF fuses (the method's ``mesh_depth``: its ``mesh.depth`` output, PGSR's unbiased depth) is rendered from
the final checkpoint in the chosen views and compared with the scene's exact camera-z depth at the same pixel centres
(`gsbench.mesh.floor.exact_depth_maps`) on the object mask (the pixels whose first hit is the object; the whole
image, less the pixels without a surface, for a scene without masks). Per
pixel the relative error is

    e = (d − d*) / d*        (d the rendered depth, d* the exact one; e > 0: the rendered surface lies behind)

and each view reports the median of e and the fractions of pixels with |e| > 1% and > 5%. A Chamfer distance
says how far the mesh is from the surface; this says whether the depth the mesh was fused from was already
wrong (training) or was right and the fusion lost it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from gsbench.diagnostics.text_table import aligned
from gsbench.errors import ConfigError
from gsbench.mesh.floor import exact_depth_maps
from gsbench.runs.finished_run import load_finished_run

TOLERANCES = (0.01, 0.05)


def depth_errors(depth: np.ndarray, exact: np.ndarray, mask: np.ndarray) -> dict:
    """Median relative error and the fractions over `TOLERANCES` (module docstring) on ``mask & exact > 0``;
    NaN where the mask is empty. A non-finite rendered depth counts as over every tolerance."""
    keep = np.asarray(mask, bool) & (exact > 0)
    if not keep.any():
        return {"pixels": 0, "median_rel": float("nan"), **{f"over_{t:g}": float("nan") for t in TOLERANCES}}
    rel = (depth[keep] - exact[keep]) / exact[keep]
    finite = np.isfinite(rel)
    out = {"pixels": int(keep.sum()), "median_rel": float(np.median(rel[finite])) if finite.any() else float("nan")}
    for t in TOLERANCES:
        out[f"over_{t:g}"] = float(np.mean(~finite | (np.abs(np.where(finite, rel, 0.0)) > t)))
    return out


def check_run_depth(folder: Path, views) -> list[dict]:
    """One `depth_errors` row per view of the run in ``folder`` (module docstring), with ``view`` added."""
    cfg, scene, method = load_finished_run(folder, "gsbench depth")
    views = list(views)
    bad = [v for v in views if not 0 <= v < len(scene.cameras)]
    if bad:
        raise ConfigError(f"views {bad} out of range: {cfg.scene} has {len(scene.cameras)} views (0..{len(scene.cameras) - 1})")
    exact = exact_depth_maps(scene, views)
    rows = []
    for view, d_exact in zip(views, exact):
        with torch.no_grad():
            depth, _ = method.mesh_depth(scene.cameras[view], cfg)
        depth = depth.double().numpy().reshape(d_exact.shape)
        mask = np.asarray(scene.masks[view], bool) if scene.masks is not None else np.ones(d_exact.shape, bool)
        rows.append({"view": view, **depth_errors(depth, d_exact, mask)})
    return rows


def format_rows(rows: list[dict]) -> str:
    """A text table of `check_run_depth`'s rows."""
    head = ["view", "pixels", "median e %"] + [f"|e| > {100 * t:g}%" for t in TOLERANCES]
    body = [[str(r["view"]), str(r["pixels"]), f"{100 * r['median_rel']:+.2f}"]
            + [f"{r[f'over_{t:g}']:.3f}" for t in TOLERANCES] for r in rows]
    return aligned(head, body)
