"""Plain-text tables for the diagnostics' terminal output: columns right-aligned to their widest cell."""

from __future__ import annotations


def aligned(head: list[str], body: list[list[str]]) -> str:
    """``head`` and the ``body`` rows as lines of right-aligned columns separated by two spaces."""
    widths = [max(len(x) for x in col) for col in zip(head, *body)]
    return "\n".join("  ".join(c.rjust(w) for c, w in zip(line, widths)) for line in [head, *body])
