"""The meshing floor of a built-in synthetic scene: TSDF fusion of its exact depth, scored like a run. No
method can beat the mesh the same TSDF settings make from the exact depth maps at the training resolution.

`floor_report` resolves ``3dgs``'s run config on the scene (only the dataset and preset layers matter),
re-plans the scene from its ``gsbench_scene.json``, ray-casts every training camera at the training
resolution (the stored ``gt_depth/`` maps are at the generated resolution, and a downscaled depth map is not
the depth at the downscaled pixel centres), fuses the depths with `gsbench.mesh.tsdf.tsdf_fusion` as a
method's would be, and evaluates the mesh with the scene's evaluators plus ``surface_offset``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from gsbench.data.camera import Scene
from gsbench.data.meta import read_meta
from gsbench.data.similarity import decompose
from gsbench.data.synthetic.generator import plan_from_meta
from gsbench.data.synthetic.render import Renderer
from gsbench.evaluators.api import evaluate_mesh_file
from gsbench.evaluators.resolve import run_options
from gsbench.mesh.cleanup import canonical_order
from gsbench.mesh.tsdf import tsdf_fusion
from gsbench.runs.runner import load_run_scene, make_run_scene, plan_run_evaluation, resolve_run


def exact_depth_maps(scene: Scene, views=None) -> list[np.ndarray]:
    """Camera-z depth of the cameras ``views`` of ``scene`` (default: all) in the frame and at the resolution the
    scene was loaded with (a TnT scene's ``data.tnt_frame``: object-frame depth x the object-to-dataset scale /
    the scene's normalisation scale)."""
    plan = plan_from_meta(read_meta(scene.root), scene.root)
    factor = scene.cameras[0].width / plan.cameras[0].width
    renderer = Renderer(plan.rendered, specular=plan.spec.specular)  # the object and its surroundings
    cameras = [plan.cameras[i].scaled(factor) for i in (range(len(plan.cameras)) if views is None else views)]
    to_training = decompose(plan.obj_to_dataset)[0] / scene.normalisation.scale
    return [renderer.depth(cam) * to_training
            for cam in tqdm(cameras, desc="exact depth", unit="view", disable=None, leave=False)]


def floor_report(scene_name: str, *, preset: str = "cpu", overrides=(), out: Path) -> dict:
    """Fuse the exact depth of ``scene_name`` and evaluate it (module docstring); the mesh goes to
    ``out/floor.ply``. Returns `gsbench.evaluators.api.evaluate_mesh_file`'s report plus the config."""
    cfg = resolve_run("3dgs", scene_name, preset=preset, overrides=overrides)
    make_run_scene(cfg)
    scene = load_run_scene(cfg)
    depths = exact_depth_maps(scene)
    masks = scene.masks if cfg.data.use_masks and scene.masks is not None else None
    mesh = tsdf_fusion(depths, scene.cameras, cfg.mesh, scene.radius, masks=masks)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    mesh_path = out / "floor.ply"
    canonical_order(mesh).export(mesh_path)
    names = [n for n in plan_run_evaluation(cfg, scene).mesh if n != "surface_offset"] + ["surface_offset"]
    options = run_options(cfg.eval.dtu_culling, names, cfg.eval.dtu_sampled)
    report = evaluate_mesh_file(mesh_path, scene, names, options)
    report["config"] = {"preset": preset, "overrides": list(overrides), "resolution": [scene.cameras[0].width,
                        scene.cameras[0].height], "mesh": vars(cfg.mesh).copy(), "use_masks": masks is not None}
    return report
