"""The tables of error against training time (docs/report.md §10): which rows share a curve, the best curve at
each time budget, every curve at every budget, and the Pareto front over all steps. The numbers are
`gsbench.report.anytime`'s and `gsbench.report.pareto.step_points`'; this module only lays them out.
"""

from __future__ import annotations

from gsbench.report.aggregate import Board
from gsbench.report.anytime import BUDGETS, BudgetResult, Standing, first_reached, standing
from gsbench.report.joins import SCHEDULE_KEYS, Curve, Join
from gsbench.report.pareto import StepPoint
from gsbench.report.stats import ALPHA
from gsbench.report.tables import MISSING, Table, TCell, join_text, number, plain
from gsbench.report.views import p_text, slug, star

WALL_MARK = "†"
TIME_NOTE = ("Time: training CPU-seconds so far (every thread's; evaluation excluded), or the wall seconds of training "
             f"where a record has no CPU seconds ({WALL_MARK}: a value standing on such points; at one thread on a "
             "core of its own wall and CPU seconds are close, sharing the cores the wall seconds are longer).")


def minutes_text(budget: float) -> str:
    """``15 min`` for 900 seconds."""
    return f"{budget / 60:g} min"


def _mean_text(at: Standing) -> str:
    return f"{number(at.mean)}{WALL_MARK if at.wall else ''} ({len(at.reached)} pairs)"


def _not_reached_text(at: Standing, scenes: list[str]) -> str:
    """Why a curve is not eligible: the scenes it has no point on, or the pairs it has not reached."""
    covered = len({scene for scene, _ in at.reached} & set(scenes))
    if covered < len(scenes):
        return f"points on {covered}/{len(scenes)} scenes"
    return f"{sum(p is not None for p in at.reached.values())}/{len(at.reached)} pairs reached"


def joins_table(board: Board, made: list[Curve], pairs: list[Join]) -> Table | None:
    """One line per two rows of one method: on one curve or apart, and why; None when no method has two rows."""
    if not pairs:
        return None
    iterations = {row.name: join_text(row.iterations) for row in board.rows}
    rows = []
    for pair in pairs:
        if pair.joined:
            why = f"the same configuration but for the schedule's length ({join_text(SCHEDULE_KEYS)})"
        elif pair.keys is None:
            why = "no scene in common"
        else:
            why = f"they differ in {join_text(pair.keys)}"
        rows.append([plain(pair.a), plain(pair.b), plain(f"{iterations[pair.a]} / {iterations[pair.b]}"),
                     TCell("one curve" if pair.joined else "separate curves", None, "best" if pair.joined else ""),
                     plain(why)])
    joined = [curve.label for curve in made if len(curve.rows) > 1]
    notes = ["Two rows of one method share a curve when their configurations differ only in the schedule's length "
             "(docs/report.md §10.2); the iterations column gives each row's steps.",
             f"Joined curves: {join_text(joined)}." if joined else "No rows are joined: each row is its own curve."]
    return Table(f"joins-{slug(board.dataset)}", f"{board.dataset}: which rows share a curve",
                 ["row", "row", "iterations", "curves", "why"], rows, notes)


def budget_table(board: Board, results: list[BudgetResult]) -> Table:
    """Per budget: the best curve and its mean, the runner-up, the paired test of the two, how many are eligible."""
    metric = board.spec.label
    header = ["budget (CPU)", "best", f"mean {metric}", "runner-up", f"mean {metric}", "best − runner-up",
              "better on", "p (test)", "eligible"]
    rows = []
    for result in results:
        best, runner_up = (result.ranked + [None, None])[:2]
        test = result.test
        tested = test is not None and test.p is not None
        rows.append([
            TCell(minutes_text(result.budget), result.budget),
            plain(best.curve.label if best else "none eligible", style="" if best else "bad"),
            TCell(_mean_text(best), best.mean, "best") if best else plain(MISSING),
            plain(runner_up.curve.label if runner_up else MISSING),
            TCell(_mean_text(runner_up), runner_up.mean) if runner_up else plain(MISSING),
            TCell(f"{test.mean_diff:+.3f}{star(test)}" if tested else MISSING, test.mean_diff if tested else None),
            plain(f"{test.wins}/{test.n} pairs" if tested else MISSING),
            TCell(f"{p_text(test.p)} ({test.test})" if tested else MISSING, test.p if tested else None),
            TCell(f"{len(result.ranked)} of {len(result.ranked) + len(result.others)} curves", len(result.ranked)),
        ])
    notes = [
        f"A curve's value at a budget B on a (scene, seed) pair: the {metric} of its latest point with time <= B "
        f"(not reached when it has none); eligible at B: a value on each of its pairs, which cover every scene; "
        f"ranked by the mean over its pairs ({board.spec.direction}; docs/report.md §10.3). Budgets: "
        f"{join_text(minutes_text(b) for b in BUDGETS)} of one core. Why a curve is not eligible: the next table.",
        f"best − runner-up: the mean over the pairs both have of their difference at B, the pairs the best is "
        f"better on, and the paired test of the Ranks section (Wilcoxon signed-rank, or the sign test with fewer "
        f"than 6 non-zero differences); *: p < {ALPHA}.",
    ]
    return Table(f"budgets-{slug(board.dataset)}", f"{board.dataset}: the best curve at each time budget",
                 header, rows, notes)


def curves_table(board: Board, made: list[Curve], target: float | None) -> Table:
    """Per curve: its value at each budget, at no limit, and when it first reaches the accuracy ``target``."""
    metric = board.spec.label
    header = ["curve", *(f"at {minutes_text(b)}" for b in BUDGETS), f"final {metric}",
              f"first reaches {number(target)}" if target is not None else "first reaches"]
    rows = []
    for curve in made:
        cells = [plain(curve.label)]
        for budget in (*BUDGETS, float("inf")):
            at = standing(board, curve, budget)
            cells.append(TCell(_mean_text(at), at.mean) if at.eligible else
                         plain(_not_reached_text(at, board.scenes), style="bad"))
        reached = first_reached(board, curve, target) if target is not None else None
        cells.append(TCell(f"{number(reached.budget, 0)} s{WALL_MARK if reached.wall else ''}", reached.budget)
                     if reached else plain("not reached" if target is not None else MISSING))
        rows.append(cells)
    reach = ("First reaches: no curve has a final value on every scene, so there is no accuracy to reach."
             if target is None else
             f"First reaches: the smallest budget (CPU-seconds) at which the curve is eligible and its mean {metric} "
             f"is at least as good as {number(target)}, the median of the curves' final means (docs/report.md §10.3).")
    notes = [
        f"A cell: the curve's mean {metric} over its (scene, seed) pairs at that budget (CPU-seconds), where it is "
        f"eligible (the best curve at each budget: the table above); final: with no limit, its last points.",
        reach,
    ]
    return Table(f"budget-values-{slug(board.dataset)}", f"{board.dataset}: every curve at each time budget",
                 header, rows, notes)


def front_table(board: Board, steps: list[StepPoint]) -> Table:
    """The steps on the Pareto front of the board's mean panel, by time."""
    metric = board.spec.label
    rows = []
    for step in sorted((s for s in steps if s.front), key=lambda s: (s.point.time, s.curve)):
        point = step.point
        share = f" ({point.step / point.iterations:.0%})" if point.iterations else ""
        rows.append([plain(step.curve), plain(f"{point.step}{share}"), plain(str(point.iterations)),
                     TCell(f"{number(point.time, 0)}{WALL_MARK if point.wall else ''}", point.time),
                     TCell(number(point.value), point.value), plain(str(point.seeds))])
    notes = [
        f"Every step of every curve over the board's scenes (the mean panel of the figure: the means over scenes, a "
        f"step counting where every scene has it) against its training time; listed: those no other step beats in "
        f"both time and mean {metric} ({board.spec.direction}; docs/report.md §10.4). A curve's step is the mean of "
        f"its seeds' points at that step: seeds, those present on every scene.",
    ]
    return Table(f"step-front-{slug(board.dataset)}", f"{board.dataset}: Pareto front over every step",
                 ["curve", "step", "iterations", "time (s)", f"mean {metric}", "seeds"], rows, notes)
