"""One self-contained HTML page per report: inline CSS, PNG plots embedded as base64, no network.

A page is a title, a line of facts under it, and sections with stable ids
(``<section id="compare">``); a navigation bar links them.  Figures come
straight from matplotlib (Agg, never written to disk first).
"""

from __future__ import annotations

import base64
import html
import io
import os
from collections.abc import Iterable, Sequence

from twin.reports.units import fmt

STYLE = """
:root { --blue: #0072BD; --red: #A2142F; --orange: #D95319; --green: #2E7D32; --grey: #5f6368; }
* { box-sizing: border-box; }
body { font-family: "Segoe UI", Helvetica, Arial, sans-serif; margin: 0; color: #1f1f1f; background: #fafafa; }
header { background: #1f3b57; color: #fff; padding: 1em 2em 0.8em; }
header h1 { margin: 0 0 0.3em; font-size: 1.45em; font-weight: 600; }
header .facts { font-size: 0.88em; opacity: 0.92; }
header .facts span { margin-right: 1.6em; white-space: nowrap; }
nav { background: #e8edf2; padding: 0.45em 2em; font-size: 0.88em; position: sticky; top: 0; z-index: 1;
      border-bottom: 1px solid #cfd8e0; }
nav a { color: #1f3b57; margin-right: 1.3em; text-decoration: none; }
nav a:hover { text-decoration: underline; }
main { max-width: 76em; margin: 0 auto; padding: 0.5em 2em 2em; }
section { background: #fff; border: 1px solid #dde3e8; border-radius: 4px; margin: 1.1em 0; padding: 0.3em 1.2em 1em; }
section h2 { font-size: 1.12em; color: #1f3b57; border-bottom: 1px solid #e3e8ec; padding-bottom: 0.3em; }
p.note { font-size: 0.86em; color: var(--grey); margin: 0.3em 0 0.8em; }
table { border-collapse: collapse; margin: 0.5em 0 1em; font-size: 0.86em; }
th, td { border: 1px solid #d5dbe0; padding: 0.25em 0.65em; text-align: right; white-space: nowrap; }
th { background: #f0f3f6; font-weight: 600; }
td.text, th.text { text-align: left; }
td.wrap, th.wrap { text-align: left; white-space: normal; min-width: 13em; }
div.tw { overflow-x: auto; max-width: 100%; }
tr.flag td { background: #fdf0f0; }
figure { margin: 0.6em 0 1em; }
figure img { max-width: 100%; height: auto; border: 1px solid #eef0f2; }
figcaption { font-size: 0.84em; color: var(--grey); margin-top: 0.2em; }
.badge { display: inline-block; padding: 0.2em 0.7em; border-radius: 3px; font-weight: 600; color: #fff; }
.badge.ok { background: var(--green); } .badge.warn { background: var(--orange); }
.badge.bad { background: var(--red); } .badge.info { background: var(--blue); }
.lvl-alarm { color: var(--red); font-weight: 600; } .lvl-warning { color: var(--orange); font-weight: 600; }
.lvl-ok { color: var(--green); }
footer { font-size: 0.78em; color: var(--grey); text-align: center; padding: 1em; }
"""


def esc(text) -> str:
    return html.escape(str(text))


def table(rows: Sequence[dict], columns: Sequence[str] | None = None, *, text_columns: Iterable[str] = (),
          flag=None, raw_columns: Iterable[str] = (), wrap_columns: Iterable[str] = ()) -> str:
    """An HTML table of ``rows`` (dicts).  Floats are formatted with 6 significant digits; columns in
    ``text_columns`` are left-aligned; ``raw_columns`` hold HTML already; ``flag(row)`` True highlights a row."""
    if not rows:
        return '<p class="note">none</p>'
    columns = list(columns or rows[0].keys())
    text_columns, raw_columns, wrap_columns = set(text_columns), set(raw_columns), set(wrap_columns)

    def css(c):
        return ' class="wrap"' if c in wrap_columns else (' class="text"' if c in text_columns else "")

    def cell(c, v):
        cls = css(c)
        if c in raw_columns:
            return f"<td{cls}>{v}</td>"
        if isinstance(v, float):
            v = fmt(v)
        return f"<td{cls}>{esc('' if v is None else v)}</td>"

    head = "".join(f"<th{css(c)}>{esc(c)}</th>" for c in columns)
    body = []
    for r in rows:
        cls = ' class="flag"' if flag is not None and flag(r) else ""
        body.append(f"<tr{cls}>" + "".join(cell(c, r.get(c)) for c in columns) + "</tr>")
    return f"<div class=\"tw\"><table><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table></div>"


def figure(fig, caption: str = "", alt: str = "", dpi: int = 100) -> str:
    """A matplotlib figure as an embedded PNG (the figure is closed)."""
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    plt.close(fig)
    data = base64.b64encode(buf.getvalue()).decode("ascii")
    cap = f"<figcaption>{esc(caption)}</figcaption>" if caption else ""
    return f'<figure><img src="data:image/png;base64,{data}" alt="{esc(alt or caption)}">{cap}</figure>'


def note(text: str) -> str:
    return f'<p class="note">{esc(text)}</p>'


def badge(text: str, kind: str = "info") -> str:
    return f'<span class="badge {kind}">{esc(text)}</span>'


class Page:
    """Sections in order; :meth:`write` makes the file."""

    def __init__(self, title: str, facts: dict | None = None, kind: str = "") -> None:
        self.title = title
        self.facts = dict(facts or {})
        self.kind = kind
        self.sections: list[tuple[str, str, str]] = []

    def add(self, sid: str, heading: str, body: str) -> None:
        self.sections.append((sid, heading, body))

    def html(self) -> str:
        from twin import __version__

        facts = "".join(f"<span><b>{esc(k)}</b>: {esc(v)}</span>" for k, v in self.facts.items())
        nav = "".join(f'<a href="#{esc(s)}">{esc(h)}</a>' for s, h, _ in self.sections)
        secs = "\n".join(f'<section id="{esc(s)}"><h2>{esc(h)}</h2>\n{b}\n</section>' for s, h, b in self.sections)
        return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<meta name="generator" content="fpdd-twin {esc(__version__)}">
<title>{esc(self.title)}</title>
<link rel="icon" href="data:,">
<style>{STYLE}</style></head>
<body data-report="{esc(self.kind)}">
<header><h1>{esc(self.title)}</h1><div class="facts">{facts}</div></header>
<nav>{nav}</nav>
<main>
{secs}
</main>
<footer>fpdd-twin {esc(__version__)} &middot; one self-contained file: plots embedded, no network needed</footer>
</body></html>
"""

    def write(self, out_dir: str, filename: str) -> str:
        os.makedirs(out_dir, exist_ok=True)
        path = os.path.join(out_dir, filename)
        with open(path, "w", encoding="utf-8") as f:
            f.write(self.html())
        return path
