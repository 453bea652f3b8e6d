"""Which evaluators a run computes, decided before any image is decoded or any step is trained.

Every evaluator declares what it needs from a scene (`Evaluator.needs`): ``"gt"`` (its ground-truth
files, checked by its ``validate``), ``"masks"`` (object masks) or ``"held_out"`` (views not trained
on, ``data.holdout_every``). `plan_evaluation` meets each list against a scene loaded without its
images (cameras, headers, ground-truth lookup):

- ``eval.evaluators`` empty → the dataset's `DEFAULT_EVALUATORS`; one whose needs the scene does not
  meet is skipped, and the reason goes into the run record (``skipped``), so a capture without ground
  truth still trains, meshes and is judged by what can be measured (``image`` is left out, not
  skipped, when the config holds no view out: that is a choice, not something the scene lacks);
- ``eval.evaluators`` named by the user → every one must apply; otherwise one `EvaluationError`
  listing each unmet need and its fix, raised before the images are loaded.

``image`` scores renders of the held-out views (the runner renders them); every other evaluator
scores the mesh file.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from gsbench.data.camera import Scene
from gsbench.errors import EvaluationError, GsbenchError
from gsbench.evaluators.base import Evaluator
from gsbench.registry import EVALUATORS

# The evaluators a run computes when ``eval.evaluators`` is empty, per dataset (`gsbench.config.run_config.dataset_of`).
DEFAULT_EVALUATORS: dict[str, tuple[str, ...]] = {
    "dtu": ("dtu_chamfer", "normal_similarity", "silhouette", "mesh_stats", "image"),
    "tnt": ("tnt_f1", "normal_similarity", "mesh_stats", "image"),
}
IMAGE = "image"


def get_evaluator(name: str) -> Evaluator:
    """An instance of the registered evaluator ``name``; RegistryError with a suggestion otherwise."""
    return EVALUATORS.get(name)()


@dataclass(frozen=True)
class EvaluationPlan:
    """``mesh``: evaluators of the mesh file, in order; ``image``: score the held-out renders;
    ``skipped``: {evaluator: reason}; ``named``: whether the user named the list."""

    mesh: tuple[str, ...]
    image: bool
    skipped: dict = field(default_factory=dict)
    named: bool = False

    @property
    def names(self) -> tuple[str, ...]:
        """Every evaluator that runs, ``image`` last."""
        return (*self.mesh, IMAGE) if self.image else self.mesh


def unmet_need(evaluator, scene: Scene, held_out: int) -> str:
    """Why ``evaluator`` cannot score ``scene`` (empty when it can); ``held_out`` views are held out."""
    for need in evaluator.needs:
        if need == "masks" and not scene.has_masks:
            return (f"scene '{scene.name}' has no object masks (a mask/ folder, one mask per image); "
                    "fix: add masks or leave this evaluator out")
        if need == "held_out" and held_out == 0:
            return "no view is held out (data.holdout_every is 0); fix: --set data.holdout_every=8"
        if need == "gt":
            if scene.gt is None:
                return (f"no ground truth: {scene.gt_missing or 'none found'}; fix: --gt PATH, the folder holding "
                        "it (DTU: Points/ and ObsMask/; TnT: the scene's .ply, .json, _trans.txt, _COLMAP_SfM.log)")
            try:
                evaluator.validate(scene)
            except GsbenchError as exc:
                return str(exc)
    return ""


def plan_evaluation(scene: Scene, dataset: str, named, held_out: int) -> EvaluationPlan:
    """The evaluators to run on ``scene`` (module docstring); ``named`` is ``eval.evaluators``."""
    names = tuple(named) or tuple(n for n in DEFAULT_EVALUATORS.get(dataset, ("mesh_stats",))
                                  if n != IMAGE or held_out > 0)
    evaluators = {n: get_evaluator(n) for n in dict.fromkeys(names)}  # unknown names fail here, with a suggestion
    for name, evaluator in evaluators.items():
        if name != IMAGE and "mesh" not in evaluator.requires:
            raise EvaluationError(f"evaluator '{name}' needs {evaluator.requires}, not a mesh; fix: leave it out "
                                  "of eval.evaluators")
    unmet = {n: reason for n, ev in evaluators.items() if (reason := unmet_need(ev, scene, held_out))}
    if named and unmet:
        lines = "; ".join(f"{n}: {reason}" for n, reason in unmet.items())
        raise EvaluationError(f"eval.evaluators names evaluator(s) that cannot score scene '{scene.name}': {lines}")
    run = [n for n in evaluators if n not in unmet]
    return EvaluationPlan(mesh=tuple(n for n in run if n != IMAGE), image=IMAGE in run, skipped=unmet,
                          named=bool(named))


CULLING_EVALUATORS = ("dtu_chamfer", "normal_similarity")  # they take the DTU mask culling option ``cull``


def run_options(dtu_culling: str, names, dtu_sampled: bool = True) -> dict:
    """The options a run passes to its mesh evaluators ``names``: ``cull = eval.dtu_culling`` to each of
    `CULLING_EVALUATORS` (normal_similarity culls only DTU scenes, like the Chamfer it sits beside), and
    ``sampled = eval.dtu_sampled`` to dtu_chamfer."""
    options = {name: {"cull": dtu_culling} for name in names if name in CULLING_EVALUATORS}
    if "dtu_chamfer" in options:
        options["dtu_chamfer"]["sampled"] = dtu_sampled
    return options
