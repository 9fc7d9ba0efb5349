"""Self-contained HTML reports: tables and PNG plots embedded, one file to mail or archive."""

from __future__ import annotations

import base64
import html
import os
from collections.abc import Iterable, Sequence


def table(rows: Sequence[dict], columns: Sequence[str] | None = None, fmt: str = "{:.6g}") -> str:
    if not rows:
        return "<p><em>none</em></p>"
    columns = list(columns or rows[0].keys())

    def cell(v):
        if isinstance(v, float):
            return fmt.format(v)
        return html.escape(str(v))

    head = "".join(f"<th>{html.escape(c)}</th>" for c in columns)
    body = "".join("<tr>" + "".join(f"<td>{cell(r.get(c, ''))}</td>" for c in columns) + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def image(path: str, caption: str = "") -> str:
    with open(path, "rb") as f:
        data = base64.b64encode(f.read()).decode("ascii")
    cap = f"<figcaption>{html.escape(caption)}</figcaption>" if caption else ""
    return f'<figure><img src="data:image/png;base64,{data}" alt="{html.escape(caption)}">{cap}</figure>'


def write(path: str, title: str, sections: Iterable[tuple[str, str]]) -> str:
    """Write an HTML page of ``(heading, html body)`` sections; returns the path."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    parts = [f"<h2>{html.escape(h)}</h2>\n{b}" for h, b in sections]
    page = f"""<!doctype html>
<html><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>
body {{ font-family: system-ui, sans-serif; margin: 2em; max-width: 70em; color: #222; }}
table {{ border-collapse: collapse; margin: 0.5em 0 1.5em; font-size: 0.9em; }}
th, td {{ border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }}
th {{ background: #f0f0f0; }}
img {{ max-width: 100%; }}
figcaption {{ font-size: 0.85em; color: #555; }}
.alarm {{ color: #b00; font-weight: bold; }}
</style></head><body>
<h1>{html.escape(title)}</h1>
{''.join(parts)}
</body></html>
"""
    with open(path, "w", encoding="utf-8") as f:
        f.write(page)
    return path
