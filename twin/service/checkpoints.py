"""Where a rig's state lives beside its journal, and a runner's checkpoints: taken every ``checkpoint_s`` and
when it stops (the twin's state as plain data with the time of the last sample processed), restored when it
starts (a log continues after that sample; a live input keeps the detector's state, so an ongoing alarm is not
raised again). A checkpoint that cannot be restored is refused with one line, never started afresh silently."""

from __future__ import annotations

import logging
import time
from pathlib import Path

from fpdd.errors import SourceError, TwinError
from twin.service.config import ServiceConfig
from twin.service.outcome import RigFailure
from twin.service.runner_core import RunnerCore
from twin.service.checkpoint_file import Checkpoint, source_identity
from twin.service.inputs import is_live

log = logging.getLogger("twin.serve")


def journal_path(cfg: ServiceConfig, rig: str) -> Path:
    """The rig's SQLite journal."""
    return Path(cfg.journal_dir) / f"{rig}.db"


def commission_path(cfg: ServiceConfig, rig: str) -> Path:
    """Where a rig's commissioning in service (``commission_s``) is saved, next to its journal."""
    return Path(cfg.journal_dir) / f"{rig}.commission.json"


def legacy_journal_path(cfg: ServiceConfig, rig: str) -> Path:
    """Where earlier versions kept the rig's JSON-lines journal (imported once)."""
    return Path(cfg.journal_dir) / f"{rig}.alarms.jsonl"



class Checkpoints(RunnerCore):
    """A runner's checkpoints: :meth:`_resume` when it opens, :meth:`_checkpoint` when due and when it stops."""

    def _resume(self) -> None:
        cp = self.journal.load_checkpoint(self.rig.name)
        if cp is None:
            return
        self._check_bound(cp)
        if cp.fingerprint != self._fp:
            log.warning("rig %s: its configuration changed since the checkpoint of %s; starting afresh "
                        "(alarms journaled before are not raised twice)", self.rig.name,
                        time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(cp.saved_at)))
            return
        assert self.twin is not None  # made by _open
        try:
            self.twin.restore(cp.state)
        except (TwinError, ValueError, KeyError, TypeError, AttributeError) as exc:  # another version's state
            raise RigFailure(f"its checkpoint in {self.journal.checkpoint_path} cannot be restored "
                             f"({type(exc).__name__}: {exc}); refused: move it aside to start the rig afresh "
                             "from its journal") from None
        self.summary.resumed_samples = cp.samples
        log.info("rig %s: resumed from its checkpoint after %d samples (t_ns=%d)", self.rig.name, cp.samples,
                 cp.t_ns)

    @property
    def _source_id(self) -> dict:
        """The rig's source as a checkpoint names it (a file's length read once, when the rig starts)."""
        sid = self.__dict__.get("_source_identity")
        if sid is None:
            sid = self.__dict__["_source_identity"] = source_identity(self.rig.source)
        return sid

    def _check_bound(self, cp: Checkpoint) -> None:
        """Refuse, in one line, a checkpoint of another numbering (epoch) or of another file than the rig's source
        now (sealed under the journal's key: :mod:`twin.service.checkpoint_file`)."""
        where = self.journal.checkpoint_path
        epoch = self.journal.epoch(self.rig.name)
        if cp.epoch and epoch and cp.epoch != epoch and self.journal.adopt_epoch(
                self.rig.name, cp.epoch, replica=self.cfg.failover is not None):
            # no alarm of the rig numbered here yet, or a standby of a failover group resuming the owner's replicated
            # checkpoint: its numbering is the checkpoint's (the owner's)
            log.info("rig %s: numbering its alarms in the checkpoint's epoch %s", self.rig.name, cp.epoch)
        elif cp.epoch and epoch and cp.epoch != epoch:
            raise RigFailure(f"its checkpoint in {where} was taken in epoch {cp.epoch} of the rig's alarms, the journal "
                             f"numbers them in epoch {epoch}; refused: move the checkpoint aside to start the rig "
                             "afresh from its journal")
        if is_live(self.rig.source) or not cp.source:
            return
        now = source_identity(self.rig.source)
        if cp.source.get("uri") == now.get("uri") and "bytes" in cp.source and cp.source.get("bytes") != now.get("bytes"):
            raise RigFailure(f"its checkpoint in {where} resumes {cp.source['uri']} of {cp.source['bytes']} bytes, "
                             f"the file has {now.get('bytes', 'no')} bytes now (another log under that name); refused: "
                             "move the checkpoint aside to start the rig afresh from its journal")

    def _checkpoint(self) -> None:
        self._last_cp = time.monotonic()
        twin = self.twin
        self.journal.retry()
        if twin is None or twin.last_t_ns is None or twin.commissioning is not None:
            return  # nothing tracked yet (a restart during the commissioning gathers its window again)
        try:
            saved = self.journal.save_checkpoint(Checkpoint(self.rig.name, twin.last_t_ns, twin.stats.samples,
                                                            self._fp, twin.state(), time.time(),
                                                            source=self._source_id))
            if self.cfg.failover is not None:  # to the standbys (twin.service.replication)
                self.outbox.publish_checkpoint(saved, self.summary.state)
            if self._cp_error:
                log.warning("rig %s: checkpoints are written again", self.rig.name)
            self._cp_error = None
        except SourceError as exc:
            if self._cp_error is None:
                log.error("rig %s: %s", self.rig.name, exc)
            self._cp_error = str(exc)

