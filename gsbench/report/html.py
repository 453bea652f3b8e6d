"""The report as an HTML page: inline CSS and a small inline script that sorts any table by a click on its header
(cells by their ``data-sort`` number when they have one, else by their text; empty keys last). The page loads
nothing from the network; its pictures are linked (``plots/<name>`` beside it) or embedded as ``data:`` URIs.
"""

from __future__ import annotations

import base64
import html
import re

from gsbench.report.tables import Plot, Section, Table

STYLE = """
body { font: 14px/1.45 system-ui, sans-serif; margin: 1.5em auto; max-width: 1200px; padding: 0 1em; color: #222; }
h1 { font-size: 1.6em; } h2 { border-bottom: 1px solid #ccc; margin-top: 2em; } h3 { font-size: 1.05em; }
nav a { margin-right: 1em; }
table { border-collapse: collapse; margin: 0.5em 0; font-size: 13px; }
th, td { border: 1px solid #ddd; padding: 3px 8px; text-align: right; white-space: nowrap; }
th:first-child, td:first-child { text-align: left; }
th { background: #f2f2f2; cursor: pointer; user-select: none; }
th[data-dir="asc"]::after { content: " \\25B2"; } th[data-dir="desc"]::after { content: " \\25BC"; }
td.best { font-weight: bold; background: #e6f4e6; }
td.reported { font-style: italic; color: #555; background: #f6f3ea; }
td.bad { color: #a33; }
td.front { color: #b04000; font-weight: bold; }
ul.notes { font-size: 12px; color: #555; }
.warn { background: #fff4e0; border: 1px solid #e0b060; padding: 0.5em 1em; }
img { max-width: 100%; border: 1px solid #eee; }
.scroll { overflow-x: auto; }
"""

SCRIPT = """
(function () {
  function key(cell) {
    if (!cell) return null;
    var v = cell.hasAttribute("data-sort") ? cell.getAttribute("data-sort") : cell.textContent.trim();
    if (v === "" || v === "\\u2013") return null;
    var n = Number(v);
    return isNaN(n) ? v.toLowerCase() : n;
  }
  document.querySelectorAll("table.sortable").forEach(function (table) {
    table.querySelectorAll("thead th").forEach(function (th, col) {
      th.addEventListener("click", function () {
        var dir = th.getAttribute("data-dir") === "asc" ? -1 : 1;
        table.querySelectorAll("thead th").forEach(function (h) { h.removeAttribute("data-dir"); });
        th.setAttribute("data-dir", dir === 1 ? "asc" : "desc");
        var body = table.tBodies[0], rows = Array.prototype.slice.call(body.rows);
        rows.sort(function (a, b) {
          var x = key(a.cells[col]), y = key(b.cells[col]);
          if (x === y) return 0;
          if (x === null) return 1;
          if (y === null) return -1;
          if (typeof x !== typeof y) return (typeof x === "number" ? -1 : 1) * dir;
          return (x < y ? -1 : 1) * dir;
        });
        rows.forEach(function (r) { body.appendChild(r); });
      });
    });
  });
})();
"""


def _inline(text: str) -> str:
    """Escape, then turn Markdown ``**bold**`` and ```code``` into <strong> and <code>."""
    text = re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", html.escape(text))
    return re.sub(r"`(.+?)`", r"<code>\1</code>", text)


def _table(table: Table) -> str:
    head = "".join(f"<th>{html.escape(h)}</th>" for h in table.header)
    body = []
    for row in table.rows:
        cells = []
        for cell in row:
            sort = f' data-sort="{cell.sort!r}"' if cell.sort is not None else ""
            style = f' class="{cell.style}"' if cell.style else ""
            title = ' title="reported on the real dataset by the paper; not comparable with synthetic scenes"' \
                if cell.style == "reported" else ""
            cells.append(f"<td{sort}{style}{title}>{html.escape(cell.text)}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    notes = "".join(f"<li>{_inline(n)}</li>" for n in table.notes)
    heading = f"<h3>{html.escape(table.title)}</h3>\n" if table.title else ""
    return (f'{heading}<div class="scroll"><table class="sortable" id="{html.escape(table.anchor)}">'
            f'<thead><tr>{head}</tr></thead>\n<tbody>\n'
            + "\n".join(body) + "\n</tbody></table></div>\n" + (f'<ul class="notes">{notes}</ul>\n' if notes else ""))


def _plot(plot: Plot, embed: bool) -> str:
    source = f"data:image/png;base64,{base64.b64encode(plot.png).decode('ascii')}" if embed else \
        f"plots/{html.escape(plot.name)}"
    return f'<p><img alt="{html.escape(plot.alt)}" src="{source}"></p>\n'


def document_html(title: str, intro: list[str], sections: list[Section], warnings: list[str], generated: str, *,
                  embed: bool = False) -> str:
    """The page: title, generation time, intro, a section index, the sections, the warnings; ``embed`` puts the
    pictures in the page."""
    nav = "".join(f'<a href="#{html.escape(s.anchor)}">{html.escape(s.title)}</a>' for s in sections)
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{html.escape(title)}</title>",
        f"<style>{STYLE}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f"<p>Generated {html.escape(generated)}.</p>",
        *(f"<p>{_inline(p)}</p>" for p in intro),
        f"<nav>{nav}</nav>",
    ]
    if warnings:
        items = "".join(f"<li>{html.escape(w)}</li>" for w in warnings)
        parts.append(f'<div class="warn"><strong>Warnings</strong><ul>{items}</ul></div>')
    for section in sections:
        parts.append(f'<h2 id="{html.escape(section.anchor)}">{html.escape(section.title)}</h2>')
        parts += [f"<p>{_inline(p)}</p>" for p in section.paragraphs]
        parts += [_table(b) if isinstance(b, Table) else _plot(b, embed) for b in section.blocks]
    parts.append(f"<script>{SCRIPT}</script>")
    parts.append("</body></html>")
    return "\n".join(parts) + "\n"
