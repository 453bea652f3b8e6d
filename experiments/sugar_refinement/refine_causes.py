"""Why SuGaR's refinement renders the held-out views worse than its coarse model: the refinement of one finished
SuGaR run trained again from its coarse model with one thing switched at a time, its held-out PSNR taken along
the way (experiments/sugar_refinement/README.md, "Held-out PSNR on the real scan 65").

    python experiments/sugar_refinement/refine_causes.py RUN_DIR OUT_DIR --variant NAME [--steps N]
        [--points 100,400,...]

RUN_DIR: a finished ``sugar`` run (``config.yaml``, ``checkpoint-final.pt``). The refinement is the run's own
(`gsbench.methods.sugar_refine`) on the ``long`` schedule (SuGaR's 15 000 steps scaled: 3 000 at the cpu preset);
every schedule runs 5 of SuGaR's steps per step whatever its length, so its first 400 and 1 400 steps are the
``short`` and ``medium`` refinements (but for the last Adam step, which a run skips). Variants:

- ``as-run``: the refinement as the method runs it;
- ``sh-full``: the SH degree at its maximum from the first step (SuGaR raises it by one every 1 000 steps from 0);
- ``undecimated``: bound to the coarse Poisson mesh as the coarse run evaluates it (each part at most
  ``mesh.poisson_triangles``), not to its parts decimated to ``method.refine_triangles``;
- ``free``: the same Gaussians, initial values and learning rates, but free: centre (the vertices' lr), rotation
  and three scales learned directly, not bound to the mesh (and no mesh normal-consistency term: there is no mesh).

Each variant trains in OUT_DIR/<variant>/ (its checkpoints: a rerun resumes); OUT_DIR/results.jsonl gets one line
per point: the variant, the seed, the step, the held-out PSNR and SSIM (the ``image`` evaluator, inside the masks when the run
uses them), the training seconds so far and the Gaussians. The coarse model's line (variant ``coarse``, step 0) is
written first, with its PSNR at SH degree 0 too.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import torch
import trimesh
import yaml

from gsbench.data.method_scene import scene_for_method
from gsbench.evaluators.resolve import get_evaluator
from gsbench.methods.sugar_refine import SUGAR_COARSE_STEPS, BoundGaussians, SugarRefinement, refinement_config
from gsbench.raster.types import RasterGaussians
from gsbench.registry import METHODS
from gsbench.runs.runner import load_run_scene, resolve_recorded
from gsbench.training.gaussians import check_finite_params
from gsbench.training.trainer import Trainer, load_checkpoint

VARIANTS = ("as-run", "sh-full", "undecimated", "free")
DEFAULT_POINTS = (50, 100, 200, 400, 800, 1400, 2000)


def held_out_scores(method, scene, cfg) -> dict:
    """Mean PSNR and SSIM of ``method``'s renders of the held-out views (as `gsbench.runs.runner._evaluate`)."""
    held_out = scene.held_out_views
    with torch.no_grad():
        renders = [method.render_image(scene.cameras[i]).clamp(0, 1).numpy() for i in held_out]
    use_masks = bool(cfg.data.use_masks and scene.masks is not None)
    result = get_evaluator("image").evaluate(renders, scene, indices=tuple(held_out), use_masks=use_masks)
    return {k: float(v) for k, v in result["metrics"].items()}


class Refinement(SugarRefinement):
    """The method's refinement, its schedules run at ``sugar_steps_per_step`` of SuGaR's steps per step whatever the
    run's length (`main`: SuGaR's 15 000 coarse steps over the coarse run's), with the SH degree at its maximum from
    the first step when ``full_sh``."""

    sugar_steps_per_step = 5.0
    full_sh = False

    def _sugar_steps_per_step(self) -> float:
        return self.sugar_steps_per_step

    def update_schedules(self, step: int, scale: float) -> None:
        super().update_schedules(step, scale)
        if self.full_sh:
            self.sh_degree = self.cfg.raster.sh_degree


class FreeGaussians(torch.nn.Module):
    """Unbound 3D Gaussians: centres (N, 3), quaternions (N, 4), log-scales (N, 3), opacity logits, SH; the
    parameter named ``vertices`` holds the centres so that the refinement's lr schedule drives them."""

    def __init__(self, bound: BoundGaussians):
        super().__init__()
        with torch.no_grad():
            g = bound.raster_input()
        self.max_sh_degree = bound.max_sh_degree
        self.params = torch.nn.ParameterDict({
            "vertices": torch.nn.Parameter(g.means.detach().clone()),
            "rotation": torch.nn.Parameter(g.quats.detach().clone()),
            "log_scales": torch.nn.Parameter(torch.log(g.scales.detach()).clone()),
            "opacity_logits": torch.nn.Parameter(bound.params["opacity_logits"].detach().clone()),
            "sh_dc": torch.nn.Parameter(bound.params["sh_dc"].detach().clone()),
            "sh_rest": torch.nn.Parameter(bound.params["sh_rest"].detach().clone())})

    def __len__(self) -> int:
        return int(self.params["vertices"].shape[0])

    def check_finite(self) -> None:
        check_finite_params(self.params)

    def raster_input(self, filter3d=None) -> RasterGaussians:
        p = self.params
        return RasterGaussians(means=p["vertices"], quats=p["rotation"], scales=torch.exp(p["log_scales"]),
                               opacities=torch.sigmoid(p["opacity_logits"][:, 0]), sh=p["sh_dc"],
                               sh_rest=p["sh_rest"] if p["sh_rest"].shape[1] else None)


class Unbound(Refinement):
    """The refinement's Gaussians as initialised, then free (`FreeGaussians`); the vertices' lr (scale S of the
    bound mesh's vertex count) for their centres."""

    def unbind(self) -> "Unbound":
        self.vertex_count = len(self.gaussians.params["vertices"])
        self.gaussians = FreeGaussians(self.gaussians)
        self.optimizer = self.make_optimizer(self.gaussians)
        return self

    def vertex_lr_scale(self) -> float:
        if isinstance(self.gaussians, BoundGaussians):
            return super().vertex_lr_scale()
        return 10.0 * self.extent / math.sqrt(self.vertex_count)


def coarse_model(run: Path):
    """(SuGaR trained, the scene without its ground truth, the scene, the run's config) of a finished run."""
    cfg = resolve_recorded(yaml.safe_load((run / "config.yaml").read_text()))
    scene = load_run_scene(cfg)
    given = scene_for_method(scene, "sugar")
    coarse = METHODS.get("sugar")()
    coarse.setup(given, cfg)
    coarse.load_state_dict(load_checkpoint(run / "checkpoint-final.pt")["method"])
    return coarse, given, scene, cfg


def cached_mesh(path: Path, make) -> trimesh.Trimesh:
    """The mesh in ``path`` (vertices, faces, vertex colours if it has them), made by ``make()`` and stored there the
    first time."""
    if not path.is_file():
        mesh = make()
        colours = mesh.visual.vertex_colors if mesh.visual.kind == "vertex" else np.zeros((0, 4), np.uint8)
        np.savez(path, vertices=mesh.vertices, faces=mesh.faces, colours=colours)
    data = np.load(path)
    colours = data["colours"] if len(data["colours"]) else None
    return trimesh.Trimesh(data["vertices"], data["faces"], vertex_colors=colours, process=False)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--variant", choices=VARIANTS, required=True)
    parser.add_argument("--steps", type=int, default=0, help="stop after this many steps (default: the long schedule)")
    parser.add_argument("--points", default=",".join(map(str, DEFAULT_POINTS)))
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    results = args.out / "results.jsonl"

    coarse, given, scene, cfg = coarse_model(args.run)
    if not results.is_file():
        line = {"variant": "coarse", "seed": cfg.seed, "step": 0, **held_out_scores(coarse, scene, cfg),
                "gaussians": len(coarse.gaussians)}
        full_degree, coarse.sh_degree = coarse.sh_degree, 0
        line["psnr_sh0"] = held_out_scores(coarse, scene, cfg)["psnr"]
        coarse.sh_degree = full_degree
        results.write_text(json.dumps(line) + "\n")

    cfg = dataclasses.replace(cfg, method={**cfg.method, "refinement": "long"})
    coarse.params = dataclasses.replace(coarse.params, refinement="long")
    second_cfg = refinement_config(cfg)
    if args.steps:
        second_cfg = dataclasses.replace(second_cfg, train=dataclasses.replace(second_cfg.train, iterations=args.steps))
    if args.variant == "undecimated":
        mesh = cached_mesh(args.out / "mesh-coarse.npz", lambda: coarse.coarse_mesh(given, cfg.mesh, cfg.seed))
    else:
        mesh = cached_mesh(args.out / "mesh-decimated.npz", lambda: coarse.refinement_mesh(given, cfg))
    model = (Unbound if args.variant == "free" else Refinement).from_coarse(coarse, mesh, second_cfg)
    model.sugar_steps_per_step = SUGAR_COARSE_STEPS / cfg.train.iterations
    model.full_sh = args.variant == "sh-full"
    if args.variant == "free":
        model = model.unbind()
        second_cfg = dataclasses.replace(second_cfg, losses={k: v for k, v in second_cfg.losses.items()
                                                             if k != "mesh_normal_consistency"})
    model.cfg = second_cfg

    def point(method, trained) -> None:
        line = {"variant": args.variant, "seed": cfg.seed, "step": trained.steps, **held_out_scores(method, scene, cfg),
                "train_seconds": trained.seconds, "gaussians": trained.num_gaussians}
        with open(results, "a") as out:
            out.write(json.dumps(line) + "\n")
        print(json.dumps(line), flush=True)

    points = [int(p) for p in args.points.split(",") if p]
    trained = Trainer(model, given, second_cfg, args.out / args.variant, points=points, on_point=point).fit()
    point(model, trained)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
