"""The long-format leaderboard CSV: one line per (board, row, scene) with the mean, its interval, the
paired test against the best row and the row's cost."""

from __future__ import annotations

import csv
import io

from gsbench.report.aggregate import Board, Stat, speed_stats
from gsbench.report.collect import Run
from gsbench.report.stats import (
    PairedTest,
    mean_ranks,
    scene_ranks,
    significance_ranks,
)

CSV_COLUMNS = ("dataset", "metric", "unit", "higher_is_better", "method", "variant", "scene", "n_ok", "n_other",
               "n_missing", "mean", "std", "best", "complete", "reported", "iterations", "threads", "train_s",
               "train_cpu_s", "total_s", "train_peak_rss_mib", "gaussians", "ci95_low", "ci95_high", "rank", "rank_paired")


def _csv_number(value) -> str:
    return "" if value is None else f"{value:.6g}"


def leaderboard_csv(boards: list[Board], tests: list[dict[tuple[str, str], PairedTest]]) -> str:
    """Long format: one line per (dataset, row, scene) and one ``scene=mean`` line per row. ``ci95_low`` /
    ``ci95_high``: the 95% t-interval of a cell's mean over seeds (n ≥ 2); ``rank``: the rank on the scene,
    or on the mean line the mean rank; ``rank_paired``: the significance rank (`gsbench.report.stats`) from
    ``tests``, each board's paired tests (`comparisons`), in the order of ``boards``."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for k, board in enumerate(boards):
        spec = board.spec
        best = {column: board.best(column) for column in [*board.scenes, "mean"]}
        per_scene = scene_ranks(board)
        mean_rank = mean_ranks(board, per_scene)
        shared = significance_ranks(board, tests[k])
        for row in board.rows:
            variant = row.runs[0].variant if row.runs else ""
            method = row.methods[0] if len(row.methods) == 1 else ";".join(row.methods)
            ref = board.reported.get(method)
            base = [board.dataset, spec.name, spec.unit, int(spec.higher_is_better), method, variant]
            for scene in board.scenes:
                cell = row.cells.get(scene)
                runs = cell.runs if cell else []
                statuses = cell.statuses if cell else {}
                value = cell.stat if cell else None
                writer.writerow(base + [scene, statuses.get("ok", 0),
                                        sum(n for k, n in statuses.items() if k not in ("ok", "missing")),
                                        statuses.get("missing", 0),
                                        _csv_number(value.mean if value else None),
                                        _csv_number(value.std if value else None), int(row.name in best[scene]), "",
                                        _csv_number(ref.scene_value(scene) if ref else None)] + _csv_speed(runs)
                                + [*_csv_interval(value), _csv_number(per_scene[row.name].get(scene)), ""])
            mean, complete = board.mean(row)
            counts = row.counts
            writer.writerow(base + ["mean", counts.get("ok", 0),
                                    sum(n for k, n in counts.items() if k not in ("ok", "missing")),
                                    counts.get("missing", 0), _csv_number(mean), "", int(row.name in best["mean"]),
                                    int(complete), _csv_number(ref.mean if ref else None)] + _csv_speed(row.runs)
                            + ["", "", _csv_number(mean_rank[row.name]), _csv_number(shared.get(row.name))])
    return out.getvalue()


def _csv_interval(value: Stat | None) -> list[str]:
    interval = value.interval if value else None
    return [_csv_number(interval[0]), _csv_number(interval[1])] if interval else ["", ""]


def _csv_speed(runs: list[Run]) -> list[str]:
    iterations = ";".join(str(i) for i in sorted({r.iterations for r in runs if r.iterations is not None}))
    threads = ";".join(str(t) for t in sorted({r.threads for r in runs if r.threads is not None}))
    means = speed_stats(runs)
    rss = means["train_rss"].mean / 2**20 if means["train_rss"] else None
    return [iterations, threads, _csv_number(means["train"].mean if means["train"] else None),
            _csv_number(means["train_cpu"].mean if means["train_cpu"] else None),
            _csv_number(means["total"].mean if means["total"] else None), _csv_number(rss),
            _csv_number(means["gaussians"].mean if means["gaussians"] else None)]
