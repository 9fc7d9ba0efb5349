"""The service's console (stderr) written by a thread of its own, so a console that stalls never stalls a rig.

``twin serve`` prints every alarm and its log lines to stderr. When whoever
reads stderr stops reading (a pipe read only at the end, a paused terminal,
a stuck log collector), a plain ``print`` blocks as soon as the pipe is full,
and with it the loop that publishes alarms or the rig that logged. Here the
lines go into a bounded queue that one thread writes out; when the queue is
full (the console has been stuck for ``capacity`` lines) further lines are
dropped and counted, and the count is written once the console moves again.
The alarms themselves are never dropped: they are journaled and published
before their line is printed.
"""

from __future__ import annotations

import logging
import queue
import sys
import threading
from typing import TextIO

#: Lines kept while the console does not move.
CAPACITY = 10000


class Console:
    """A non-blocking writer of lines to ``stream`` (default ``sys.stderr``)."""

    def __init__(self, stream: TextIO | None = None, capacity: int = CAPACITY) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self._q: queue.Queue[tuple[str, int] | None] = queue.Queue(maxsize=capacity)
        self._lock = threading.Lock()
        self.dropped = 0
        self._since = 0  # dropped since the last line queued: said before the next one, where they were lost
        self._thread = threading.Thread(target=self._write, name="console", daemon=True)
        self._thread.start()

    def line(self, text: str) -> None:
        """Queue one line; never blocks (a full queue drops it and counts it)."""
        with self._lock:
            try:
                self._q.put_nowait((text, self._since))
                self._since = 0
            except queue.Full:
                self.dropped += 1
                self._since += 1

    @staticmethod
    def _lost(n: int) -> str:
        return f"twin serve: {n} console line(s) dropped: the console was not read\n"

    def _write(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            text, lost = item
            try:
                self.stream.write((self._lost(lost) if lost else "") + text + "\n")
                self.stream.flush()
            except (OSError, ValueError):  # the console is gone: nothing to write to any more
                return

    def close(self, timeout: float = 5.0) -> bool:
        """Write what is queued (waiting up to ``timeout`` for a stuck console); ``True`` if all was written."""
        with self._lock:
            if self._since:
                try:
                    self._q.put((self._lost(self._since).rstrip("\n"), 0), timeout=timeout)
                    self._since = 0
                except queue.Full:
                    return False
        try:
            self._q.put(None, timeout=timeout)
        except queue.Full:
            return False
        self._thread.join(timeout)
        return not self._thread.is_alive()


class ConsoleHandler(logging.Handler):
    """A logging handler that writes through a :class:`Console`."""

    def __init__(self, console: Console) -> None:
        super().__init__()
        self.console = console

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.console.line(self.format(record))
        except Exception:  # noqa: BLE001 - logging must not raise into the rig
            self.handleError(record)


def install(level: int, prefix: str = "twin serve: ", stream: TextIO | None = None) -> Console:
    """Route the root logger through a new :class:`Console` (replacing its handlers); returns the console."""
    console = Console(stream)
    handler = ConsoleHandler(console)
    handler.setFormatter(logging.Formatter(prefix + "%(message)s"))
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(handler)
    root.setLevel(level)
    return console
