"""Writing a report: one CSV per table, and the whole report as Markdown and as HTML (the
figures are PNG files beside them, linked relatively)."""
from __future__ import annotations

import html
import os
from dataclasses import dataclass, field
from typing import Any

from ...plumbing import safeout
from .stats import round_half_up
from .tables import Column, Table


@dataclass
class Figure:
    path: str        # relative to the report folder
    caption: str


@dataclass
class Section:
    title: str
    paragraphs: list[str] = field(default_factory=list)
    bullets: list[str] = field(default_factory=list)
    tables: list[Table] = field(default_factory=list)
    figures: list[Figure] = field(default_factory=list)
    anchor: str = ""


@dataclass
class Document:
    title: str
    info: list[tuple[str, str]]
    sections: list[Section]


# ---------------------------------------------------------------------------------------------
# value formatting
# ---------------------------------------------------------------------------------------------

def _is_fixed(f: str) -> bool:
    return len(f) >= 2 and f[0] == "f" and f[1:].isdigit()


def fmt_display(v: Any, c: Column) -> str:
    if v is None or v == "":
        return "—"
    f = c.fmt
    if f == "yesno":
        return "yes" if v else "no"
    if isinstance(v, bool):
        return str(v)
    if f == "int":
        return f"{int(v):,}"
    if _is_fixed(f):
        return f"{float(v):,.{int(f[1:])}f}"
    if f == "pct1":
        return f"{float(v):.1f}"
    if f == "g":
        return f"{float(v):g}" if isinstance(v, (int, float)) else str(v)
    return str(v)


def fmt_csv(v: Any, c: Column) -> str:
    if v is None:
        return ""
    if c.fmt == "yesno":
        return "yes" if v else "no"
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, float):
        if c.csv_nd is not None:
            v = round_half_up(v, c.csv_nd)
            if v is None:
                return ""
        if v == int(v) and abs(v) < 1e15 and not _is_fixed(c.fmt) and c.fmt != "g":
            return str(int(v))
        return repr(v)
    return str(v)


def table_csv(t: Table) -> str:
    """A table as CSV, every cell defused against spreadsheet formulas (gateway.plumbing.safeout)."""
    return safeout.csv_text([[c.key for c in t.columns],
                             *([fmt_csv(r.get(c.key), c) for c in t.columns] for r in t.rows)],
                            line_end="\n")


def write_csvs(tables: list[Table], out_dir: str) -> list[str]:
    paths = []
    for t in tables:
        p = os.path.join(out_dir, t.name + ".csv")
        _write(p, table_csv(t))
        paths.append(p)
    return paths


def _write(path: str, text: str) -> None:
    safeout.write_atomic(path, text.encode("utf-8"), make_dir=False)


# ---------------------------------------------------------------------------------------------
# Markdown
# ---------------------------------------------------------------------------------------------

#: text as one line of Markdown, escaped (line breaks, raw HTML, links, table cells): gateway.plumbing.safeout
_md_cell = safeout.md_text


def _right(c: Column) -> bool:
    return c.fmt in ("int", "pct1", "g") or _is_fixed(c.fmt)


def table_md(t: Table, level: int = 3) -> str:
    cols = [c for c in t.columns if c.show]
    out = [f"{'#' * level} {_md_cell(t.title)}", ""]
    if t.intro:
        out += [_md_cell(t.intro), ""]
    if t.rows:
        out.append("| " + " | ".join(_md_cell(c.label) for c in cols) + " |")
        out.append("|" + "|".join("---:" if _right(c) else "---" for c in cols) + "|")
        for r in t.rows:
            out.append("| " + " | ".join(_md_cell(fmt_display(r.get(c.key), c)) for c in cols) + " |")
    else:
        out.append("*(no rows)*")
    out.append("")
    out.append(f"CSV: [{_md_cell(t.name)}.csv]({safeout.md_link_target(t.name)}.csv)")
    if t.notes:
        out.append("")
        out += [f"- {_md_cell(n)}" for n in t.notes]
    out.append("")
    return "\n".join(out)


def document_md(doc: Document) -> str:
    out = [f"# {_md_cell(doc.title)}", ""]
    for k, v in doc.info:
        out.append(f"- **{_md_cell(k)}:** {_md_cell(v)}")
    out.append("")
    out.append("Contents: " + " · ".join(f"[{_md_cell(s.title)}](#{safeout.md_link_target(s.anchor)})"
                                         for s in doc.sections if s.anchor))
    out.append("")
    for s in doc.sections:
        if s.anchor:
            out.append(f'<a id="{s.anchor}"></a>')
            out.append("")
        out += [f"## {_md_cell(s.title)}", ""]
        for p in s.paragraphs:
            out += [_md_cell(p), ""]
        if s.bullets:
            out += [f"- {_md_cell(b)}" for b in s.bullets]
            out.append("")
        for t in s.tables:
            out.append(table_md(t))
        for f in s.figures:
            out += [f"![{_md_cell(f.caption)}]({safeout.md_link_target(f.path)})", "",
                    f"*{_md_cell(f.caption)}*", ""]
    return "\n".join(out).rstrip() + "\n"


# ---------------------------------------------------------------------------------------------
# HTML
# ---------------------------------------------------------------------------------------------

CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", sans-serif; margin: 2em auto; max-width: 1700px;
       padding: 0 1.5em; color: #222; line-height: 1.45; }
h1 { border-bottom: 2px solid #1f77b4; padding-bottom: .2em; }
h2 { margin-top: 2em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: .6em 0; font-size: 0.95em; }
th, td { border: 1px solid #ccc; padding: .25em .6em; }
th { background: #f0f4f8; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
tr:nth-child(even) td { background: #fafafa; }
.notes { color: #555; font-size: .92em; }
.problems li { color: #a00; }
figure { margin: 1.2em 0; }
figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { color: #444; font-style: italic; }
.info td { border: none; padding: .1em .8em .1em 0; }
"""


def table_html(t: Table) -> str:
    e = html.escape
    cols = [c for c in t.columns if c.show]
    out = [f"<h3>{e(t.title)}</h3>"]
    if t.intro:
        out.append(f"<p>{e(t.intro)}</p>")
    if t.rows:
        out.append("<table><thead><tr>" + "".join(f"<th>{e(c.label)}</th>" for c in cols) + "</tr></thead><tbody>")
        for r in t.rows:
            out.append("<tr>" + "".join(
                f'<td{" class=num" if _right(c) else ""}>{e(fmt_display(r.get(c.key), c))}</td>'
                for c in cols) + "</tr>")
        out.append("</tbody></table>")
    else:
        out.append("<p><em>(no rows)</em></p>")
    out.append(f'<p class="notes">CSV: <a href="{e(t.name)}.csv">{e(t.name)}.csv</a></p>')
    if t.notes:
        out.append('<ul class="notes">' + "".join(f"<li>{e(n)}</li>" for n in t.notes) + "</ul>")
    return "\n".join(out)


def document_html(doc: Document) -> str:
    e = html.escape
    out = ["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
           f"<title>{e(doc.title)}</title>", f"<style>{CSS}</style></head><body>",
           f"<h1>{e(doc.title)}</h1>", '<table class="info">']
    out += [f"<tr><td><b>{e(k)}</b></td><td>{e(v)}</td></tr>" for k, v in doc.info]
    out.append("</table>")
    out.append("<p>Contents: " + " · ".join(f'<a href="#{e(s.anchor)}">{e(s.title)}</a>'
                                            for s in doc.sections if s.anchor) + "</p>")
    for s in doc.sections:
        out.append(f'<h2 id="{e(s.anchor)}">{e(s.title)}</h2>')
        for p in s.paragraphs:
            out.append(f"<p>{e(p)}</p>")
        if s.bullets:
            cls = ' class="problems"' if s.anchor == "problems" else ""
            out.append(f"<ul{cls}>" + "".join(f"<li>{e(b)}</li>" for b in s.bullets) + "</ul>")
        for t in s.tables:
            out.append(table_html(t))
        for f in s.figures:
            out.append(f'<figure><a href="{e(f.path)}"><img src="{e(f.path)}" alt="{e(f.caption)}" '
                       f'loading="lazy"></a><figcaption>{e(f.caption)}</figcaption></figure>')
    out.append("</body></html>")
    return "\n".join(out) + "\n"


def write_document(doc: Document, out_dir: str) -> tuple[str, str]:
    md = os.path.join(out_dir, "report.md")
    ht = os.path.join(out_dir, "report.html")
    _write(md, document_md(doc))
    _write(ht, document_html(doc))
    return md, ht
