"""The report's tables of single runs: the measures of captures without ground truth, the evaluators skipped,
failed runs, protocols, the environment and the list of every run (`gsbench.report.views` has the
tables of boards: leaderboards, speed against error, ablations)."""

from __future__ import annotations

import json
import math

from gsbench.report.aggregate import natural_key
from gsbench.report.collect import Run
from gsbench.report.metrics import NO_GT, MetricSpec
from gsbench.report.tables import MISSING, Table, TCell, count, join_text, number, plain


def significant(value: float | None, digits: int = 4) -> str:
    """``value`` to ``digits`` significant digits in fixed notation (whole numbers in full, thousands separated)."""
    if value is None:
        return MISSING
    if value == 0 or not math.isfinite(value):
        return f"{value:g}"
    decimals = max(0, digits - 1 - math.floor(math.log10(abs(value))))
    return f"{value:,.{decimals}f}"


NO_GT_FORMAT = {  # metric -> (cell text of a value)
    "psnr": lambda v: number(v, 2), "ssim": number, "mask_iou": number,
    "outside_hull_area_share": lambda v: number(v, 4), "components": count,
    "watertight": lambda v: "yes" if v >= 0.5 else "no", "area": significant,
}


def nogt_table(runs: list[Run], specs: dict[str, MetricSpec]) -> Table:
    """One line per run with a measure that needs no ground truth (`NO_GT`): its values, training time and
    Gaussian count; sorted by dataset, scene, row, seed."""
    header = ["dataset", "scene", "method", "seed", "status"]
    header += [specs[m].label if m in specs else m for m in NO_GT] + ["train (s)", "Gaussians"]
    rows = []
    for r in sorted((r for r in runs if any(m in r.metrics for m in NO_GT)),
                    key=lambda r: (r.dataset, r.scene, natural_key(r.row), r.seed if r.seed is not None else -1,
                                   r.run_id)):
        values = [r.metrics.get(m) for m in NO_GT]
        train = r.timings.get("train")
        rows.append([plain(r.dataset), plain(r.scene), plain(r.row), TCell(str(r.seed), r.seed),
                     plain(r.status, None, "" if r.ok else "bad"),
                     *(TCell(NO_GT_FORMAT[m](v) if v is not None else MISSING, v) for m, v in zip(NO_GT, values)),
                     TCell(number(train, 1), train), TCell(count(r.num_gaussians), r.num_gaussians)])
    notes = [
        "Per run, with or without ground truth. PSNR / SSIM: renders of the held-out views (`image`); mask IoU: "
        "mean over views of |silhouette ∩ mask| / |silhouette ∪ mask| and outside-hull area share: the fraction "
        "of the surface area outside the masks' visual hull, floaters (`silhouette`); components, watertight, "
        "area: `mesh_stats`.",
        "Higher is better: PSNR, SSIM, mask IoU, watertight; lower is better: outside-hull area share, components. "
        "Area (dataset units², DTU: mm²) is descriptive, not a score. None of these ranks the leaderboards.",
        "Train: the run's wall-clock training seconds, comparable only between runs at the same thread count on an "
        "equally loaded machine of the same kind (see Environment).",
    ]
    return Table("no-ground-truth", "Measures without ground truth", header, rows, notes)


def skipped_table(runs: list[Run]) -> Table:
    """The evaluators a run's scene could not feed, with the reason, grouped by (dataset, scene,
    evaluator, reason): the methods and how many runs."""
    groups: dict[tuple, list[Run]] = {}
    for r in runs:
        for evaluator, reason in r.skipped.items():
            groups.setdefault((r.dataset, r.scene, evaluator, reason), []).append(r)
    rows = [[plain(dataset), plain(scene), plain(evaluator), plain(reason),
             plain(join_text(sorted({r.row for r in group}, key=natural_key))), TCell(str(len(group)), len(group))]
            for (dataset, scene, evaluator, reason), group in sorted(groups.items())]
    return Table("skipped-evaluators", "Evaluators skipped", ["dataset", "scene", "evaluator", "reason", "methods",
                                                              "runs"], rows,
                 ["An evaluator is skipped when the scene cannot feed it (no ground truth, no masks, no held-out "
                  "view); the run still trains, meshes and is judged by what can be measured."])


def _last_line(text: str) -> str:
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return lines[-1] if lines else ""


def failed_table(runs: list[Run]) -> Table:
    header = ["run id", "dataset", "scene", "method", "seed", "status", "last error line", "record"]
    rows = [[plain(r.run_id), plain(r.dataset), plain(r.scene), plain(r.row), plain(str(r.seed)),
             plain(r.status, None, "bad"), plain(_last_line(r.error_tail) or MISSING), plain(r.path)]
            for r in runs if not r.ok]
    return Table("failed-runs", "", header, rows)


def unfinished_table(folders: list[str]) -> Table:
    """Run folders without a record (`gsbench.report.collect.unfinished_folders`)."""
    rows = [[plain(folder), plain("no record: killed before it finished? `gsbench run` with its settings resumes it")]
            for folder in folders]
    return Table("unfinished-runs", "", ["run folder", "state"], rows)


def protocol_table(runs: list[Run]) -> Table:
    """Every evaluator protocol behind a number, per dataset: name@version, the options that differ
    between runs of that evaluator on that dataset, and run counts."""
    groups: dict[tuple, int] = {}
    for run in runs:
        for name, proto in sorted(run.eval_protocol.items()):
            if isinstance(proto, dict):
                options = json.dumps({k: v for k, v in proto.items() if k not in ("name", "version")}, sort_keys=True)
                key = (run.dataset, name, str(proto.get("version")), options)
                groups[key] = groups.get(key, 0) + 1
    siblings: dict[tuple, list[dict]] = {}
    for dataset, name, _, options in groups:
        siblings.setdefault((dataset, name), []).append(json.loads(options))
    rows = []
    for (dataset, name, version, options), n in sorted(groups.items()):
        others = siblings[(dataset, name)]
        differing = sorted({k for o in others for k in o if any(p.get(k) != o.get(k) for p in others)})
        mine = json.loads(options)
        shown = ", ".join(f"{k}={json.dumps(mine.get(k))}" for k in differing) or "same for all runs"
        rows.append([plain(dataset), plain(f"{name}@{version}"), plain(shown), TCell(str(n), n)])
    notes = ["Numbers from different versions of one evaluator are not comparable. Options: those that differ "
             "between runs of the evaluator on one dataset; some are derived per scene (e.g. a distance gate "
             "from the ground truth's point spacing), others change the protocol."]
    return Table("protocol-table", "", ["dataset", "protocol", "options", "runs"], rows, notes)


ENV_PACKAGES = ("torch", "numpy", "open3d")


def environment_table(runs: list[Run]) -> Table:
    """Distinct (CPU, cores, threads, versions, commit) combinations and how many runs each produced."""
    groups: dict[tuple, int] = {}
    for run in runs:
        env = run.environment
        packages = env.get("packages") if isinstance(env.get("packages"), dict) else {}
        commit = str(env.get("git_commit") or MISSING)[:10] + ("+dirty" if env.get("git_dirty") else "")
        key = (str(env.get("cpu") or MISSING), str(env.get("cpu_count") or MISSING),
               str(run.threads if run.threads is not None else MISSING), str(env.get("os") or MISSING),
               str(env.get("python") or MISSING), str(env.get("gsbench") or MISSING), commit,
               *(str(packages.get(p) or MISSING) for p in ENV_PACKAGES))
        groups[key] = groups.get(key, 0) + 1
    header = ["CPU", "cores", "threads", "OS", "python", "gsbench", "git", *ENV_PACKAGES, "runs"]
    rows = [[plain(v) for v in key] + [TCell(str(n), n)] for key, n in sorted(groups.items())]
    note = "One row per machine and software combination that produced runs; threads: OpenMP/torch threads."
    return Table("environment-table", "", header, rows, [note])


def runs_table(runs: list[Run], specs: dict[str, MetricSpec], sweeps: dict[str, list[str]]) -> Table:
    """Every run: identity, status, its dataset's ranking metric, times, threads, CPU model, protocols, sweeps."""
    header = ["run id", "dataset", "scene", "method", "seed", "status", "metric", "value", "train (s)", "total (s)",
              "threads", "CPU", "iterations", "protocols", "sweeps", "record"]
    rows = []
    for r in runs:
        spec = specs.get(r.dataset)
        value = r.metrics.get(spec.name) if spec else None
        protocols = ", ".join(f"{n}@{p.get('version')}" for n, p in sorted(r.eval_protocol.items())
                              if isinstance(p, dict))
        train, total = r.timings.get("train"), r.timings.get("total")
        rows.append([plain(r.run_id), plain(r.dataset), plain(r.scene), plain(r.row), TCell(str(r.seed), r.seed),
                     plain(r.status, None, "" if r.ok else "bad"), plain(spec.label if spec else MISSING),
                     TCell(number(value), value), TCell(number(train, 1), train), TCell(number(total, 1), total),
                     plain(str(r.threads if r.threads is not None else MISSING)),
                     plain(str(r.environment.get("cpu") or MISSING)),
                     plain(str(r.iterations if r.iterations is not None else MISSING)),
                     plain(protocols or MISSING), plain("; ".join(sweeps.get(r.run_id, [])) or MISSING), plain(r.path)])
    return Table("runs-table", "", header, rows)


