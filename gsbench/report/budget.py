"""Whether the Gaussian budget (``train.max_gaussians``) bound a run's densification.

A budget caps the Gaussian count; a run that reaches it early spends it on whatever it densified
first, so two methods compared under a binding budget are compared at that budget, not as the papers
ran them. A run was *cut* when its record's ``densify_budget.first_cut_step`` is set: a refinement
left densification candidates out (docs/training.md §6). Records written before that was
tracked have no ``densify_budget``; of them only the final count is known, and the report says how
many *ended* at `NEAR` · ``max_gaussians`` or more, a different statement: a method that prunes hard
after its densification (SuGaR) can have been cut and still end far below the budget.
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass

from gsbench.report.collect import Run
from gsbench.report.tables import MISSING, count

NEAR = 0.95


@dataclass(frozen=True)
class BudgetUse:
    """One run against its budget: ``budget`` (``max_gaussians``; None without one); ``recorded``:
    whether the record tracks cuts; ``reached``: cut (recorded) or ended at `NEAR` of the budget or
    more (not recorded); ``first_cut_step``: None if never cut or not recorded."""

    budget: int | None
    recorded: bool = False
    reached: bool = False
    first_cut_step: int | None = None


def budget_use(run: Run) -> BudgetUse:
    """`BudgetUse` of ``run`` from its record (module docstring)."""
    budget = run.config.get("train.max_gaussians")
    if not isinstance(budget, int) or isinstance(budget, bool) or budget <= 0:
        return BudgetUse(None)
    if run.densify_budget:
        step = run.densify_budget.get("first_cut_step")
        return BudgetUse(budget, True, step is not None, step)
    final = run.num_gaussians
    return BudgetUse(budget, False, final is not None and final >= NEAR * budget)


def budget_text(runs: list[Run]) -> str:
    """A row's budget cell over its ok runs with a budget: ``k/n cut at B, from step s`` (s: the median
    first cut step) for records that track cuts, ``k/n ended ≥ 95% of B`` for those that do not."""
    uses = [u for u in (budget_use(r) for r in runs if r.ok) if u.budget is not None]
    parts = []
    for recorded in (True, False):
        group = [u for u in uses if u.recorded == recorded]
        if not group:
            continue
        reached = [u for u in group if u.reached]
        budgets = "/".join(count(b) for b in sorted({u.budget for u in group}))
        if recorded:
            text = f"{len(reached)}/{len(group)} cut at {budgets}"
            steps = [u.first_cut_step for u in reached]
            parts.append(text + (f", from step {statistics.median_low(steps)}" if steps else ""))
        else:
            parts.append(f"{len(reached)}/{len(group)} ended ≥ {NEAR:.0%} of {budgets} (cuts not recorded)")
    return "; ".join(parts) or MISSING


BUDGET_NOTE = (f"Gaussian budget (train.max_gaussians), over a row's ok runs with one: 'k/n cut at B, from step "
               f"s': k runs had densification candidates left out by the budget, from the median step s at which "
               f"that first happened; 'ended ≥ {NEAR:.0%} of B (cuts not recorded)': records from before cuts "
               f"were tracked, of which only the final count is known (a method that prunes after densifying "
               f"can have been cut and end lower). Rows cut by the budget are compared at that budget: a method "
               f"that densifies faster, or into the surroundings, has less of it left for the object.")
