"""Entry points for the CLI (``gsbench eval``): look up evaluators, score a mesh file, print a table."""

from __future__ import annotations

from pathlib import Path

from gsbench.data.camera import Scene
from gsbench.errors import RegistryError
from gsbench.evaluators.resolve import get_evaluator, plan_evaluation


def default_evaluators(scene: Scene) -> tuple[str, ...]:
    """The dataset's default mesh evaluators that apply to ``scene`` (`gsbench.evaluators.resolve`)."""
    return plan_evaluation(scene, "tnt" if scene.fmt == "tnt" else "dtu", (), held_out=0).mesh


def evaluate_mesh_file(mesh_path, scene: Scene, names=None, options: dict | None = None) -> dict:
    """Score one mesh with each evaluator in ``names`` (default: `default_evaluators`).

    ``options`` maps an evaluator name to its keyword options. Returns
    ``{"mesh": path, "scene": name, "results": {evaluator: {"metrics", "protocol", "diagnostics"}}}``.
    Every evaluator is validated first, so a missing GT file fails before any long computation.
    """
    names = tuple(names) if names else default_evaluators(scene)
    evaluators = {n: get_evaluator(n) for n in names}
    for ev in evaluators.values():
        if "mesh" not in ev.requires:
            raise RegistryError(f"evaluator '{ev.name}' needs {ev.requires}, not a mesh file")
        ev.validate(scene)
    results = {n: ev.evaluate(mesh_path, scene, **(options or {}).get(n, {})) for n, ev in evaluators.items()}
    return {"mesh": str(Path(mesh_path)), "scene": scene.name, "results": results}


def format_table(report: dict) -> str:
    """A small fixed-width text table of an `evaluate_mesh_file` report, warnings and skipped evaluators
    (``report["skipped"]``, {name: reason}) listed below it."""
    rows = [("evaluator", "metric", "value", "unit", "better")]
    better = {True: "higher", False: "lower", None: "(describes)"}
    warnings = []
    for name, res in report["results"].items():
        info = get_evaluator(name).metrics
        for metric, value in res["metrics"].items():
            mi = info[metric]
            rows.append((f"{name}@{res['protocol']['version']}", metric, f"{value:.4f}", mi.unit,
                         better[mi.higher_is_better]))
        warnings += [f"warning ({name}): {w}" for w in res["diagnostics"].get("warnings", [])]
    skipped = [f"skipped ({name}): {reason}" for name, reason in report.get("skipped", {}).items()]
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(f"{c:<{w}}" for c, w in zip(r, widths)).rstrip() for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines + warnings + skipped)
