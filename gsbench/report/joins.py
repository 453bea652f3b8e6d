"""Which rows of a board share one curve of error against time (docs/report.md §10.2).

A curve is a method's trade of time for error, so runs of one method whose configurations differ only in the
schedule's length lie on one curve, and the report joins them: their rows (e.g. two presets) become one curve.
The schedule's length is `SCHEDULE_KEYS`: ``train.iterations``, from which the trainer scales every step-valued
setting at run time (docs/training.md §1), so the record's other step settings are the paper's and equal. Keys
that do not change what a run computes are left out of the comparison (`INERT_KEYS`: a run's identity and
execution, the preset's name, whose settings are keys of their own, how often it checkpoints and logs, its
evaluation points). Any other difference keeps the rows apart: the bench preset's resolution (``data.max_size``)
and Gaussian budget (``train.max_gaussians``) change what each step costs and what the run can reach, so the
cpu and bench rows of a method are separate curves, drawn side by side.
"""

from __future__ import annotations

from dataclasses import dataclass

from gsbench.report.aggregate import Board, Row
from gsbench.report.collect import NOT_A_VARIANT, PRESET_KEY, Run, show_value

SCHEDULE_KEYS = ("train.iterations",)
INERT_KEYS = (*NOT_A_VARIANT, PRESET_KEY, "train.checkpoint_every", "train.log_every")


@dataclass(frozen=True)
class Curve:
    """One curve of a board: its rows (one, or several joined), named by the method and each row's variant."""

    label: str
    method: str
    rows: tuple[Row, ...]

    @property
    def runs(self) -> list[Run]:
        return [run for row in self.rows for run in row.runs]


def compared_config(run: Run) -> dict[str, str]:
    """The run's configuration without `SCHEDULE_KEYS` and `INERT_KEYS`, each value as shown in row labels."""
    return {key: show_value(value) for key, value in run.config.items() if key not in (*SCHEDULE_KEYS, *INERT_KEYS)}


def differing_keys(a: Row, b: Row) -> list[str] | None:
    """The keys outside `SCHEDULE_KEYS` and `INERT_KEYS` in which a run of ``a`` and a run of ``b`` on one scene
    differ (a key one of them lacks differs), sorted; None when the rows share no scene (nothing to compare)."""
    shared = sorted(set(a.cells) & set(b.cells))
    if not shared:
        return None
    keys: set[str] = set()
    for scene in shared:
        for run_a in a.cells[scene].runs:
            for run_b in b.cells[scene].runs:
                config_a, config_b = compared_config(run_a), compared_config(run_b)
                keys |= {k for k in config_a.keys() | config_b.keys() if config_a.get(k) != config_b.get(k)}
    return sorted(keys)


def _label(method: str, rows: list[Row]) -> str:
    if len(rows) == 1:
        return rows[0].name
    variants = [row.name.removeprefix(method).strip() or "[base]" for row in rows]
    return f"{method} {' + '.join(variants)}"


def curves(board: Board) -> list[Curve]:
    """The board's rows grouped into curves, in row order: a row joins the first curve of its method each of
    whose rows it differs from in the schedule's length alone (`differing_keys` empty), else starts one."""
    groups: list[list[Row]] = []
    for row in board.rows:
        for group in groups:
            if group[0].methods == row.methods and all(differing_keys(row, other) == [] for other in group):
                group.append(row)
                break
        else:
            groups.append([row])
    return [Curve(_label(group[0].methods[0], group), group[0].methods[0], tuple(group)) for group in groups]


@dataclass(frozen=True)
class Join:
    """Two rows of one method: joined on one curve, or kept apart by ``keys`` (None: no scene in common)."""

    a: str
    b: str
    joined: bool
    keys: list[str] | None


def joins(board: Board, made: list[Curve]) -> list[Join]:
    """Every pair of rows of one method on ``board``, in row order, with whether ``made`` joins them."""
    curve_of = {row.name: curve.label for curve in made for row in curve.rows}
    pairs = []
    for i, a in enumerate(board.rows):
        for b in board.rows[i + 1:]:
            if a.methods == b.methods:
                pairs.append(Join(a.name, b.name, curve_of[a.name] == curve_of[b.name], differing_keys(a, b)))
    return pairs
