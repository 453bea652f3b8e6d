"""Figures of the report as PNG bytes (matplotlib, a dependency of gsbench), drawn on the Agg canvas
without pyplot, so no global backend state or display is touched.

- `speed_figure`: per dataset, four panels (training time, total time, peak RSS in training, Gaussians) against
  the mean metric, with their 95% intervals (grey bars, `gsbench.report.pareto.Point`); rows with every
  scene are filled and compete for the Pareto front (joined by a line), incomplete rows are hollow.
- `grid_figure`: a one-key numeric sweep (e.g. IBGS K) against the metric, one line per scene, error
  bars = sample std over seeds.
- `variants_figure`: a sweep of named rows, the metric per row (one marker per scene, std bars).
- `curves_figure`: per dataset, the metric against training CPU-seconds (log scale), a panel per scene and one
  for the mean over scenes, one curve per `gsbench.report.joins.Curve` with its min–max band over seeds
  (docs/report.md §10.1), the time budgets dotted, the steps on the Pareto front ringed; its legend names each
  curve whole (`legend_labels`).
"""

from __future__ import annotations

import io
import math
import textwrap

from gsbench.errors import missing_dependency
from gsbench.report.aggregate import Board
from gsbench.report.anytime import BUDGETS, board_series
from gsbench.report.joins import curves
from gsbench.report.pareto import COSTS, cost_points, step_points
from gsbench.report.png import compact

SCALE = {"train_rss": 1 / 2**20}  # bytes -> MiB on the memory axis
LABEL_CHARS = 40
LEGEND_CHARS = 110  # a wrapped legend line of the curves figure, at 7 pt about 6 inches
LEGEND_LINE_INCHES = 0.16


def _figure(width: float, height: float):
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: PLC0415
        from matplotlib.figure import Figure  # noqa: PLC0415
    except ImportError as exc:
        fix = "pip install matplotlib, a dependency of gsbench (or run gsbench report --no-plots)"
        raise missing_dependency("matplotlib", fix) from exc
    figure = Figure(figsize=(width, height), dpi=100, layout="constrained")
    FigureCanvasAgg(figure)
    return figure


def _png(figure) -> bytes:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", metadata={"Software": None})
    return compact(buffer.getvalue())


def _short(text: str) -> str:
    """Long row names keep their start (the method) and their end (the last differing value)."""
    if len(text) <= LABEL_CHARS:
        return text
    head = LABEL_CHARS // 3
    return text[:head] + "…" + text[-(LABEL_CHARS - head - 1):]


def legend_labels(labels: list[str]) -> tuple[list[str], int]:
    """(the legend's texts, its columns): each label whole when every one fits in `LABEL_CHARS` (two columns),
    else each wrapped at `LEGEND_CHARS` in one column. Never elided: rows of one method that differ only in the
    middle of their names (their start and end alike) would read as one."""
    if all(len(label) <= LABEL_CHARS for label in labels):
        return list(labels), 2
    return [textwrap.fill(label, LEGEND_CHARS, break_on_hyphens=False) for label in labels], 1


def _legend_inches(texts: list[str], columns: int) -> float:
    """The height of the legend of `legend_labels`' texts in ``columns`` columns (its lines shared among them)."""
    return LEGEND_LINE_INCHES * math.ceil(sum(text.count("\n") + 1 for text in texts) / columns)


def _metric_axis(board: Board) -> str:
    return f"mean {board.spec.label} ({board.spec.direction})"


def speed_figure(board: Board) -> bytes | None:
    """Cost against the mean metric with Pareto fronts; None when no row has a cost and a metric."""
    panels = {cost: cost_points(board, cost) for cost in COSTS}
    if not any(panels.values()):
        return None
    figure = _figure(11, 8)
    axes = figure.subplots(2, 2).ravel()
    for ax, (cost, points) in zip(axes, panels.items()):
        scale = SCALE.get(cost, 1.0)
        ax.set_xlabel(COSTS[cost][1])
        ax.set_ylabel(_metric_axis(board))
        ax.grid(alpha=0.3)
        for point in points:
            if point.cost_ci is not None or point.value_ci is not None:  # the 95% intervals (`Point`)
                ax.errorbar([point.cost * scale], [point.value], fmt="none", ecolor="0.55", elinewidth=0.9,
                            capsize=2, zorder=2, yerr=None if point.value_ci is None else [point.value_ci],
                            xerr=None if point.cost_ci is None else [point.cost_ci * scale])
            ax.scatter([point.cost * scale], [point.value], s=40, zorder=3,
                       facecolors="C0" if point.complete else "none", edgecolors="C3" if point.front else "C0")
            ax.annotate(_short(point.row), (point.cost * scale, point.value), fontsize=7,
                        xytext=(4, 3), textcoords="offset points")
        front = sorted((p.cost * scale, p.value) for p in points if p.front)
        if front:
            ax.plot(*zip(*front), color="C3", lw=1.2, zorder=2, label="Pareto front")
            ax.legend(fontsize=8, loc="best")
        if not points:
            ax.text(0.5, 0.5, "no data", ha="center", va="center", transform=ax.transAxes)
    figure.suptitle(f"{board.dataset}: cost against {board.spec.label} (hollow: not every scene)")
    return _png(figure)


def _scene_series(board: Board, positions) -> list[tuple[int, str, list, list, list]]:
    """Per scene with any value: (index, scene, positions, means, stds) over the rows at ``positions``."""
    series = []
    for i, scene in enumerate(board.scenes):
        points = [(at, row.cells[scene].stat) for at, row in zip(positions, board.rows)
                  if row.cells.get(scene) is not None and row.cells[scene].stat is not None]
        if points:
            series.append((i, scene, [at for at, _ in points], [st.mean for _, st in points],
                           [st.std or 0.0 for _, st in points]))
    return series


def grid_figure(board: Board) -> bytes | None:
    """Metric against the swept value, one line per scene; None when nothing has a value."""
    series = _scene_series(board, board.grid_values)
    if not series:
        return None
    figure = _figure(7, 4.5)
    ax = figure.subplots()
    for i, scene, xs, ys, errs in series:
        ax.errorbar(xs, ys, yerr=errs, marker="o", capsize=3, color=f"C{i}", label=scene)
    ax.set_xlabel(board.grid_key)
    ax.set_ylabel(f"{board.spec.label} ({board.spec.direction})")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(board.title, fontsize=10)
    return _png(figure)


def variants_figure(board: Board) -> bytes | None:
    """One horizontal line per sweep label, a marker per scene with std bars; None when empty."""
    series = _scene_series(board, range(len(board.rows)))
    if not series:
        return None
    figure = _figure(8, 1.2 + 0.4 * len(board.rows))
    ax = figure.subplots()
    for i, scene, ys, xs, errs in series:
        ax.errorbar(xs, ys, xerr=errs, fmt="o", capsize=3, color=f"C{i}", label=scene)
    ax.set_yticks(range(len(board.rows)), [_short(row.name) for row in board.rows], fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel(f"{board.spec.label} ({board.spec.direction})")
    ax.grid(alpha=0.3, axis="x")
    ax.legend(fontsize=8)
    ax.set_title(board.title, fontsize=10)
    return _png(figure)


MARKERS = "osD^v"  # a joined curve's schedule lengths, shortest first
LINE_STYLES = ("-", "--", ":", "-.")  # a method's curves, in row order
PANEL_INCHES = (3.6, 2.7)


def _curve_styles(made) -> dict[str, tuple[str, str]]:
    """Curve label -> (colour, line style): a colour per method, a line style per curve of that method."""
    methods: dict[str, list[str]] = {}
    for curve in made:
        methods.setdefault(curve.method, []).append(curve.label)
    return {label: (f"C{m % 10}", LINE_STYLES[k % len(LINE_STYLES)])
            for m, labels in enumerate(methods.values()) for k, label in enumerate(labels)}


def curves_figure(board: Board) -> bytes | None:
    """The board's curves of error against training time (module docstring); None when no curve has a point."""
    made = curves(board)
    panels = board_series(board, made)
    if not any(panels.values()):
        return None
    columns = 2 if len(panels) == 4 else min(3, len(panels))
    lines = math.ceil(len(panels) / columns)
    legend_texts, legend_columns = legend_labels([curve.label for curve in made])
    figure = _figure(PANEL_INCHES[0] * columns,
                     PANEL_INCHES[1] * lines + 0.4 + _legend_inches(legend_texts, legend_columns))
    axes = figure.subplots(lines, columns, squeeze=False).ravel()
    styles = _curve_styles(made)
    handles, wall = {}, False
    for ax, (scene, series) in zip(axes, panels.items()):
        for label, points in series.items():
            colour, style = styles[label]
            for k, iterations in enumerate(sorted({p.iterations for p in points})):
                run = [p for p in points if p.iterations == iterations]
                xs = [p.time for p in run]
                ax.fill_between(xs, [p.low for p in run], [p.high for p in run], color=colour, alpha=0.15, linewidth=0)
                (line,) = ax.plot(xs, [p.value for p in run], color=colour, ls=style, lw=1.1)
                handles.setdefault(label, line)
                ax.scatter(xs, [p.value for p in run], s=14, marker=MARKERS[k % len(MARKERS)], zorder=3,
                           facecolors=["none" if p.wall else colour for p in run], edgecolors=colour, linewidths=0.9)
                wall = wall or any(p.wall for p in run)
        front = sorted((s.point.time, s.point.value) for s in step_points(series, bool(board.spec.higher_is_better))
                       if s.front)
        if front:
            ax.scatter(*zip(*front), s=55, facecolors="none", edgecolors="red", linewidths=0.8, zorder=4)
        for budget in BUDGETS:
            ax.axvline(budget, color="0.55", ls=":", lw=0.8)
        ax.set_xscale("log")
        ax.set_title("mean over scenes" if scene is None else scene, fontsize=9)
        ax.set_xlabel("training CPU seconds", fontsize=7)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3, which="both", lw=0.4)
    for ax in axes[len(panels):]:
        ax.axis("off")
    figure.supylabel(f"{board.spec.label} ({board.spec.direction})", fontsize=8)
    shown = [(handles[curve.label], text) for curve, text in zip(made, legend_texts) if curve.label in handles]
    figure.legend([handle for handle, _ in shown], [text for _, text in shown], loc="outside lower center",
                  ncols=legend_columns, fontsize=7, frameon=False)
    figure.suptitle(f"{board.dataset}: error against training time; band: min–max over seeds; dotted: "
                    f"{', '.join(f'{b / 60:g}' for b in BUDGETS)} min; red rings: Pareto front"
                    + ("\nhollow markers: wall seconds (the record has no CPU seconds)" if wall else ""), fontsize=9)
    return _png(figure)
