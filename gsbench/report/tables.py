"""A small table model shared by the Markdown and HTML outputs, its Markdown renderer, and fixed
number formats (so the files are byte-stable for golden tests).

A `TCell` carries its text, an optional numeric sort key (used by the HTML sorter; None sorts last)
and a style: ``best`` (bold), ``reported`` (a paper's number), ``bad`` (failed/missing runs), ``front``
(on a Pareto front).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from gsbench.report.aggregate import Cell, Stat

MISSING = "–"


@dataclass(frozen=True)
class TCell:
    text: str
    sort: float | None = None
    style: str = ""


@dataclass
class Table:
    anchor: str
    title: str
    header: list[str]
    rows: list[list[TCell]]
    notes: list[str] = field(default_factory=list)


def number(value: float | None, digits: int = 3) -> str:
    return MISSING if value is None else f"{value:.{digits}f}"


def count(value: float | None) -> str:
    return MISSING if value is None else f"{value:,.0f}"


def mib(value: float | None) -> str:
    return MISSING if value is None else f"{value / 2**20:,.0f}"


def stat_text(value: Stat | None, digits: int = 3) -> str:
    """``mean ± h``, h the half-width of the 95% t-interval over the values (n ≥ 2); ``mean`` for one value."""
    if value is None:
        return MISSING
    spread = f" ± {value.ci:.{digits}f}" if value.ci is not None else ""
    return f"{value.mean:.{digits}f}{spread}"


def status_text(statuses: dict[str, int]) -> str:
    """``2 ok, 1 failed, 1 missing`` (statuses already in display order)."""
    return ", ".join(f"{n} {status}" for status, n in statuses.items() if n)


def metric_cell(cell: Cell | None, best: bool = False) -> TCell:
    """``mean ± 95% half-width`` over the cell's ok runs (`stat_text`), with the other statuses in brackets; ``–`` for no run."""
    if cell is None or not cell.runs:  # nothing ran: the runs column counts what is missing
        return TCell(MISSING, None, "bad")
    value = cell.stat
    others = status_text({k: n for k, n in cell.statuses.items() if k != "ok"})
    if value is None:
        return TCell(others, None, "bad")
    text = stat_text(value) + (f" ({others})" if others else "")
    return TCell(text, value.mean, "best" if best else "")


def plain(text: str, sort: float | None = None, style: str = "") -> TCell:
    return TCell(text, sort, style)


def to_markdown(table: Table, level: int = 3) -> str:
    """The table as a Markdown section: heading, pipe table (best values bold), notes as a list."""

    def show(cell: TCell) -> str:
        text = cell.text.replace("|", "\\|").replace("*", "\\*")  # a literal * (a significance mark)
        if cell.style == "best" and text != MISSING:
            return f"**{text}**"
        return f"*{text}*" if cell.style == "reported" and text != MISSING else text

    lines = [f"{'#' * level} {table.title}", ""] if table.title else []
    if table.rows:
        lines.append("| " + " | ".join(h.replace("|", "\\|") for h in table.header) + " |")
        lines.append("|" + "|".join("---" for _ in table.header) + "|")
        lines += ["| " + " | ".join(show(c) for c in row) + " |" for row in table.rows]
    else:
        lines.append("(none)")
    if table.notes:
        lines.append("")
        lines += [f"- {note}" for note in table.notes]
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class Plot:
    """A figure: ``name`` is its file under ``plots/``."""

    name: str
    alt: str
    png: bytes


@dataclass
class Section:
    """A part of the report: paragraphs, then tables and plots in order."""

    anchor: str
    title: str
    paragraphs: list[str] = field(default_factory=list)
    blocks: list = field(default_factory=list)  # Table | Plot


def document_markdown(title: str, intro: list[str], sections: list[Section], warnings: list[str]) -> str:
    """The whole report as Markdown; plots are linked as ``plots/<name>``; warnings last."""
    parts = [f"# {title}\n", *(f"{p}\n" for p in intro)]
    for section in sections:
        parts.append(f"## {section.title}\n")
        parts += [f"{p}\n" for p in section.paragraphs]
        for block in section.blocks:
            parts.append(to_markdown(block) if isinstance(block, Table) else f"![{block.alt}](plots/{block.name})\n")
    if warnings:
        parts.append("## Warnings\n")
        parts.append("".join(f"- {w}\n" for w in warnings))
    return "\n".join(parts)


def join_text(values) -> str:
    """``a, b, c`` of ``values``, or the missing mark when there are none."""
    return ", ".join(str(v) for v in values) or MISSING
