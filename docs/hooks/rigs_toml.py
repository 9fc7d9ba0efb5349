"""MkDocs hook: the rigs.toml page lists every key the configuration reader knows.

On the page that holds ``<!-- rigs-toml-keys -->``, every key of ``twin.service.config_parse`` (``TOP_KEYS``,
``ZENOH_KEYS``, ``SERVICE_KEYS``, ``RIG_KEYS``, ``BASELINE_KEYS``, ``NOISE_KEYS``) and of
``twin.service.ownership.FAILOVER_KEYS`` must appear in a table row as ``| `table.key` |``: a key the reader
knows and the page does not list is a warning, which fails ``mkdocs build --strict``.
"""

from __future__ import annotations

import logging

MARKER = "<!-- rigs-toml-keys -->"
log = logging.getLogger("mkdocs.hooks.rigs_toml")


def known_keys() -> list[str]:
    from twin.service import config_parse as keys
    from twin.service.ownership import FAILOVER_KEYS

    tables = {"zenoh": keys.ZENOH_KEYS, "service": keys.SERVICE_KEYS, "failover": FAILOVER_KEYS,
              "rig": keys.RIG_KEYS, "baseline": keys.BASELINE_KEYS, "noise": keys.NOISE_KEYS}
    return [f"{table}.{key}" for table, names in tables.items() for key in names]


def on_page_markdown(markdown: str, page, config, files) -> str:
    if MARKER not in markdown:
        return markdown
    missing = [key for key in known_keys() if f"| `{key}` |" not in markdown]
    if missing:
        log.warning("%s: keys the configuration reader knows and the page does not list: %s",
                    page.file.src_path, ", ".join(missing))
    return markdown.replace(MARKER, "")
