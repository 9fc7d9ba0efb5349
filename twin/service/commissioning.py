"""A rig commissioned in service (``commission_s``): its first seconds gathered, fitted in a process of its own
(:class:`twin.service.spawn.FitJob`) while the other rigs go on, the outcome saved beside the journal and used
by the next runs."""

from __future__ import annotations

import logging
import os
import time

from fpdd.errors import FilterError, TwinError
from twin.service.checkpoints import commission_path
from twin.service.outcome import RigFailure, Stopped
from twin.service.rig import fingerprint
from twin.service.runner_core import RunnerCore
from twin.service.spawn import FitJob

log = logging.getLogger("twin.serve")


class Commissioner(RunnerCore):
    """A runner's commissioning: a saved one restored, the fit started once the window is gathered and finished."""

    def _saved_commission(self):
        """A commissioning saved by an earlier run (``commission_s``): it wins over commissioning again."""
        if not self.rig.commission_s:
            return None
        path = commission_path(self.cfg, self.rig.name)
        if not path.exists():
            return None
        from twin.online.commission import apply_commission, describe, load_fit

        try:
            com = load_fit(str(path))
            self.rig = apply_commission(self.rig, com)
        except TwinError as exc:
            log.warning("rig %s: its saved commissioning cannot be used (%s); commissioning again", self.rig.name,
                        exc)
            return None
        self._fp = fingerprint(self.rig, self.cfg.estimate_every)
        self._notes = f"commissioned by an earlier run ({path.name}): {describe(com, self.rig.track)}"
        log.info("rig %s: %s", self.rig.name, self._notes)
        return com

    def _commission(self, wait: bool) -> None:
        """Start the commissioning fit once the window is gathered; finish the commissioning once it is done
        (``wait``: until then, the rig's status going on; a replayed log waits, a live input does not)."""
        twin = self.twin
        assert twin is not None  # made by _open
        c = twin.commissioning
        if c is None or not c.window.full:
            return
        if self._fit is None:
            try:
                self._fit = FitJob(self.rig, c.window.samples())
            except (OSError, RuntimeError, ValueError) as exc:  # no process for the fit: the rig goes on all the same
                self._end_commission(None, f"the fit's process cannot start ({type(exc).__name__}: {exc})")
                return
            c.fitting = True
            log.info("rig %s: %s", self.rig.name, c.note())
            twin.publish_status(force=True)
            self.outbox.flush()
        while not self._fit.done():
            if not wait:
                return
            if self.stop.wait(0.5):
                raise Stopped
            twin.publish_status()
            self.outbox.flush(force=False)
        self._finish_fit()

    def _commission_steps(self):
        """:meth:`_commission` for a replayed log, which waits for the fit: yields while it runs."""
        self._commission(wait=False)
        while self._fit is not None and not self._fit.done():
            yield time.monotonic() + 0.5
            if self.stop.is_set():
                raise Stopped
            assert self.twin is not None  # made by _open
            self.twin.publish_status()
            self.outbox.flush(force=False)
        if self._fit is not None:
            self._finish_fit()

    def _finish_fit(self) -> None:
        assert self._fit is not None
        doc, problem = self._fit.result()
        self._fit = None
        self._end_commission(doc, problem)

    def _end_commission(self, doc: dict | None, problem: str) -> None:
        twin = self.twin
        assert twin is not None  # made by _open
        com = None
        if doc is not None:
            com = self._save_commission(doc)
        try:
            line = twin.finish_commissioning(com, problem)
        except FilterError as exc:
            raise RigFailure(f"{exc} (right after its commissioning)") from None
        self.rig = twin.rig
        self._fp = fingerprint(self.rig, self.cfg.estimate_every)
        self._notes = line
        (log.info if com is not None else log.warning)("rig %s: %s", self.rig.name, line)
        self._checkpoint()
        self.outbox.flush()

    def _save_commission(self, doc: dict):
        """Save a commissioning next to the journal (atomically) and read it back; unsaved, it is used all the same."""
        import json

        from twin.online.commission import from_dict, load_fit

        path = commission_path(self.cfg, self.rig.name)
        tmp = path.with_name(path.name + ".tmp")
        try:
            tmp.write_text(json.dumps(doc, indent=2, allow_nan=False))
            os.replace(tmp, path)
            return load_fit(str(path))
        except (OSError, ValueError, TwinError) as exc:
            log.error("rig %s: its commissioning cannot be saved to %s (%s); it is used but a restart "
                      "commissions again", self.rig.name, path, exc)
            return from_dict(doc, f"commissioning of {self.rig.name} (not saved)")

