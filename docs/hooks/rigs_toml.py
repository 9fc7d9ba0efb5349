"""MkDocs hook: the rigs.toml page lists every key the configuration reader knows.

On the page that holds ``<!-- rigs-toml-keys -->``, every key of ``twin.service.config`` (``TOP_KEYS``,
``ZENOH_KEYS``, ``SERVICE_KEYS``, ``RIG_KEYS``, ``BASELINE_KEYS``, ``NOISE_KEYS``) and of
``twin.service.ownership.FAILOVER_KEYS`` must appear in a table row as ``| `table.key` |``: a key the reader
knows and the page does not list is a warning, which fails ``mkdocs build --strict``.
"""

from __future__ import annotations

import logging

MARKER = "<!-- rigs-toml-keys -->"
log = logging.getLogger("mkdocs.hooks.rigs_toml")


def known_keys() -> list[str]:
    from twin.service import config
    from twin.service.ownership import FAILOVER_KEYS

    tables = {"zenoh": config.ZENOH_KEYS, "service": config.SERVICE_KEYS, "failover": FAILOVER_KEYS,
              "rig": config.RIG_KEYS, "baseline": config.BASELINE_KEYS, "noise": config.NOISE_KEYS}
    return [f"{table}.{key}" for table, keys in tables.items() for key in keys]


def on_page_markdown(markdown: str, page, config, files) -> str:
    if MARKER not in markdown:
        return markdown
    missing = [key for key in known_keys() if f"| `{key}` |" not in markdown]
    if missing:
        log.warning("%s: keys the configuration reader knows and the page does not list: %s",
                    page.file.src_path, ", ".join(missing))
    return markdown.replace(MARKER, "")
