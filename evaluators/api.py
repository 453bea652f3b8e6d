"""Entry points for the CLI (``gsbench eval``): look up evaluators, score a mesh file, print a table.

Before a mesh file is scored, the memory its evaluators need is estimated from its vertex and face counts
(`evaluation_memory`, from the file's header where the format has one, `gsbench.mesh.files.header_counts`),
and a mesh that cannot fit in the memory available is refused at once (`check_evaluation_memory`). Each
evaluator's ``memory_per_face`` is its peak resident memory above the loaded scene, divided by the faces, on
the exact surface of synthetic/spot subdivided to 6.0 M faces (3.0 M vertices; spot-tnt's to 7.3 M for
tnt_f1): dtu_chamfer 354 bytes, normal_similarity 305, silhouette 346, mesh_stats 371, surface_offset 267,
tnt_f1 396, each class holding its own rounded up to tens. At a quarter of those sizes they took 1.0 to 1.7
times as much a face (their fixed part, the ground truth's and the masks', spread over fewer faces).
dtu_chamfer's downsampling grows faster than its faces (`dtu_chamfer.check_downsample_memory` checks it when
its points are known).
"""

from __future__ import annotations

import time
from pathlib import Path

from gsbench.data.camera import Scene
from gsbench.errors import EvaluationError, RegistryError
from gsbench.evaluators.geometry import read_geometry
from gsbench.evaluators.resolve import get_evaluator, plan_evaluation
from gsbench.mesh.files import FACES_PER_VERTEX, header_counts
from gsbench.resources import available_memory_bytes, memory_size
from gsbench.training.progress import format_duration

DECIMATION = ("pymeshlab's meshing_decimation_quadric_edge_collapse(targetfacenum=N), or MeshLab's Quadric Edge "
              "Collapse")


def default_evaluators(scene: Scene) -> tuple[str, ...]:
    """The dataset's default mesh evaluators that apply to ``scene`` (`gsbench.evaluators.resolve`)."""
    return plan_evaluation(scene, "tnt" if scene.fmt == "tnt" else "dtu", (), held_out=0).mesh


def mesh_counts(mesh) -> tuple[int, int]:
    """(vertices, faces) of a mesh file, from its header where the format has one (PLY, OFF, binary STL),
    else from reading it; of a mesh object, its own."""
    counts = header_counts(mesh) if isinstance(mesh, (str, Path)) and Path(mesh).is_file() else None
    if counts is None:
        geo = read_geometry(mesh)
        counts = len(geo.vertices), 0 if geo.faces is None else len(geo.faces)
    return counts


def evaluation_memory(names, counts: tuple[int, int]) -> dict[str, int]:
    """Bytes each evaluator of ``names`` needs at its peak for a mesh of ``counts`` (vertices, faces): its
    `Evaluator.memory_per_face` times max(faces, 2 vertices) (`FACES_PER_VERTEX`: a point of a point cloud, or
    of a mesh whose vertices are not shared, counts as a closed mesh's vertex would)."""
    faces = max(counts[1], FACES_PER_VERTEX * counts[0])
    return {n: get_evaluator(n).memory_per_face * faces for n in names}


def check_evaluation_memory(label, names, counts: tuple[int, int], available: int | None = None) -> None:
    """EvaluationError when the largest of `evaluation_memory` (the evaluators run one at a time) exceeds the
    memory available (`gsbench.resources.available_memory_bytes`, unless given), naming each evaluator's
    share and the face count that would fit; nothing when the available memory is not known."""
    available = available_memory_bytes() if available is None else available
    items = evaluation_memory(names, counts)
    if available is None or not items or max(items.values()) <= available:
        return
    ranked = sorted(items.items(), key=lambda kv: -kv[1])
    parts = ", ".join(f"{name} {memory_size(size)}" for name, size in ranked)
    fits = available // max(get_evaluator(n).memory_per_face for n in names)
    fits -= fits % 10 ** max(0, len(str(fits)) - 2)  # two significant digits, rounded down
    raise EvaluationError(
        f"{label}: {counts[0]:,} vertices and {counts[1]:,} faces need about {memory_size(ranked[0][1])} to evaluate "
        f"({parts}; one evaluator at a time, the scene and its ground truth on top) but {memory_size(available)} is "
        f"available; fix: decimate the mesh to at most {fits:,} faces ({DECIMATION}), leave out {ranked[0][0]} "
        "(name the other evaluators: --evaluator, or eval.evaluators in a run), or run it on a larger machine")


def evaluate_mesh_file(mesh_path, scene: Scene, names=None, options: dict | None = None, progress=None) -> dict:
    """Score one mesh with each evaluator in ``names`` (default: `default_evaluators`).

    ``options`` maps an evaluator name to its keyword options. Returns
    ``{"mesh": path, "scene": name, "results": {evaluator: {"metrics", "protocol", "diagnostics"}}}``.
    Every evaluator is validated first, so a missing GT file fails before any long computation, and the
    memory they need is checked (`check_evaluation_memory`). ``progress``: called with a line as each
    evaluator starts (e.g. `gsbench.training.progress.stage`).
    """
    names = tuple(names) if names else default_evaluators(scene)
    evaluators = {n: get_evaluator(n) for n in names}
    for ev in evaluators.values():
        if "mesh" not in ev.requires:
            raise RegistryError(f"evaluator '{ev.name}' needs {ev.requires}, not a mesh file")
        ev.validate(scene)
    counts = mesh_counts(mesh_path)
    check_evaluation_memory(mesh_path, names, counts)
    memory, results, start = evaluation_memory(names, counts), {}, time.perf_counter()
    for i, (name, ev) in enumerate(evaluators.items(), start=1):
        if progress is not None:
            step = f"{name} ({i}/{len(evaluators)}, about {memory_size(memory[name])}"
            progress(f"evaluating {mesh_path} ({counts[0]:,} vertices, {counts[1]:,} faces): {step})" if i == 1 else
                     f"evaluating {step}; {format_duration(time.perf_counter() - start)} so far)")
        results[name] = ev.evaluate(mesh_path, scene, **(options or {}).get(name, {}))
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
