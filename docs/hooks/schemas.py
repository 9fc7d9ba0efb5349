"""MkDocs hook: the message schemas page is generated from the schemas the code validates and writes.

A page that holds ``<!-- schemas:rig -->`` or ``<!-- schemas:twin -->`` gets, for every MCAP topic and Foxglove channel the product writes, the
topic, the schema's name as registered in the MCAP file (its ``title``), a table of its fields (type, required,
description) and the whole JSON schema. The sources: :mod:`replay.mcapio.layout` (rig signals) and
:func:`twin.service.live_view.messages.topics` (the twin's events, as the MCAP and the live view carry them).
"""

from __future__ import annotations

import json
from typing import Any

RIG = "<!-- schemas:rig -->"
TWIN = "<!-- schemas:twin -->"


def _type(prop: dict[str, Any]) -> str:
    t = prop.get("type")
    if isinstance(t, list):
        t = " or ".join(t)
    if t is None and "$ref" in prop:
        t = prop["$ref"]
    if "enum" in prop:
        t = f"{t}: " + ", ".join(f"`{v}`" for v in prop["enum"])
    return str(t or "")


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _fields(schema: dict[str, Any]) -> str:
    props = schema.get("properties", {})
    required = set(schema.get("required", []))
    rows = ["| field | type | required | description |", "|---|---|---|---|"]
    for name, prop in props.items():
        rows.append(f"| `{name}` | {_cell(_type(prop))} | {'yes' if name in required else ''} | "
                    f"{_cell(prop.get('description', ''))} |")
    return "\n".join(rows)


def _rig_topics() -> list[tuple[str, dict[str, Any]]]:
    """What a rig log in MCAP carries (``twin simulate -o rec.mcap``, ``replay convert``, ``replay record``)."""
    from replay.mcapio import layout

    signals = ["x_ref", "u", "x", "pA", "pB"]
    return [(layout.SIGNALS_TOPIC, layout.signals_schema(signals)), (layout.BLOCK_TOPIC, layout.block_schema(signals))]


def _twin_topics() -> list[tuple[str, dict[str, Any]]]:
    """What the twin writes: its MCAP (``twin track``, a rig's ``record``) and the Foxglove live view's channels
    (the live view's ``/rig/signals`` adds the display units)."""
    from twin.models import DEFAULT_MODEL
    from twin.service.live_view.messages import topics

    return list(topics(DEFAULT_MODEL).values())


def generate(items: list[tuple[str, dict[str, Any]]]) -> str:
    parts = ["| topic | schema name | content |", "|---|---|---|"]
    for topic, schema in items:
        parts.append(f"| `{topic}` | `{schema.get('title', '')}` | {_cell(schema.get('description', ''))} |")
    parts.append("")
    for topic, schema in items:
        parts.append(f"### `{topic}`: `{schema.get('title', '')}`\n")
        if schema.get("description"):
            parts.append(_cell(schema["description"]) + "\n")
        parts.append(_fields(schema) + "\n")
        parts.append('??? note "The whole JSON schema"\n\n    ```json\n' +
                     "\n".join("    " + line for line in json.dumps(schema, indent=2).splitlines()) +
                     "\n    ```\n")
    return "\n".join(parts)


def on_page_markdown(markdown: str, page, config, files) -> str:
    if RIG in markdown:
        markdown = markdown.replace(RIG, generate(_rig_topics()))
    if TWIN in markdown:
        markdown = markdown.replace(TWIN, generate(_twin_topics()))
    return markdown
