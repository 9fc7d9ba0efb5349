"""MkDocs hook: the Python API reference lists every public name of ``twin`` and ``replay``.

A page that holds ``<!-- api-reference -->`` gets, for every name in ``twin._EXPORTS`` and ``replay._EXPORTS``
(the curated API ``import twin`` and ``import replay`` expose), a heading and a mkdocstrings block of the module
that defines it, so the reference follows the exports and the docstrings, never a hand-kept list.
"""

from __future__ import annotations

MARKER = "<!-- api-reference -->"


def generate() -> str:
    import replay
    import twin

    parts: list[str] = []
    for package, exports in (("twin", twin._EXPORTS), ("replay", replay._EXPORTS)):
        parts.append(f"## `{package}`\n")
        for name, module in exports.items():
            if package == "replay" and name in twin._EXPORTS:
                continue  # the error tree is one, listed under twin
            parts.append(f"### `{package}.{name}`\n\nDefined in `{module}`.\n\n::: {module}.{name}\n"
                         "    options:\n      show_root_heading: false\n      show_root_toc_entry: false\n      heading_level: 4\n")
    return "\n".join(parts)


def on_page_markdown(markdown: str, page, config, files) -> str:
    if MARKER not in markdown:
        return markdown
    return markdown.replace(MARKER, generate())
