"""Make the CAN reference logs in tests/data/ (run from the repository root).

``python tests/data/make_can_reference.py`` writes

* ``msp25_pycan_reference.log`` and ``msp25_pycan_reference.asc`` — made
  independently of fpdd-twin's writers: the frames are encoded with ``cantools``
  (``Message.encode``), sent on a python-can ``virtual`` bus and recorded by
  python-can's own ``can.Logger`` through a ``can.Notifier``, as
  ``python -m can.logger -i virtual`` would.  0.2 s of MSP25 traffic with known
  values (x = 10 um * k, x_ref = 12 um * k, u = 5 mV * k, pA = 10000 + 10 k kPa,
  pB = 5000 kPa, pP = 21000 kPa, T_oil = 45.0 degC for control cycle k) plus one
  frame of a foreign id 0x7FF;
* ``msp25_short.{asc,blf,log,trc}`` — the project's own writers
  (:class:`replay.can.logs.CanLogSink`) on 50 ms of the benchmark's seeded signals
  (:func:`benchmarks.can.msp25_samples`, seed 0).
"""

from __future__ import annotations

import threading
from pathlib import Path

import can
import cantools

HERE = Path(__file__).resolve().parent
DBC = HERE.parent.parent / "replay" / "data" / "msp25.dbc"
T0 = 1_700_000_000.0  # s, a whole second so every format stores the start time exactly
CYCLES = 200  # 1 ms control cycles


def reference_messages() -> list[can.Message]:
    """The independent reference traffic, time ordered (timestamps in s)."""
    db = cantools.database.load_file(str(DBC))
    pos, valve = db.get_message_by_name("MSP25_Position"), db.get_message_by_name("MSP25_Valve")
    pres, hpu = db.get_message_by_name("MSP25_Pressure"), db.get_message_by_name("HPU_Status")
    out = []
    cnt_p = 0
    for k in range(CYCLES):
        t = T0 + k * 1e-3
        out.append(can.Message(timestamp=t, arbitration_id=pos.frame_id, is_extended_id=False,
                               data=pos.encode({"x": 10.0 * k, "x_ref": 12.0 * k})))
        out.append(can.Message(timestamp=t + 100e-6, arbitration_id=valve.frame_id, is_extended_id=False,
                               data=valve.encode({"u": 5.0 * k, "RollCnt": k % 256, "CtrlMode": 1})))
        if k % 2 == 0:
            out.append(can.Message(timestamp=t + 200e-6, arbitration_id=pres.frame_id, is_extended_id=False,
                                   data=pres.encode({"pA": 10000 + 10 * k, "pB": 5000, "RollCnt": cnt_p % 256})))
            cnt_p += 1
        if k % 100 == 0:
            out.append(can.Message(timestamp=t + 300e-6, arbitration_id=hpu.frame_id, is_extended_id=False,
                                   data=hpu.encode({"pP": 21000, "T_oil": 45.0, "HPU_State": 3,
                                                    "RollCnt": (k // 100) % 16})))
        if k == 50:
            out.append(can.Message(timestamp=t + 400e-6, arbitration_id=0x7FF, is_extended_id=False,
                                   data=b"\xde\xad\xbe\xef"))
    return out


def record_with_python_can(path: Path) -> None:
    """Send the reference traffic on a virtual bus and log it with can.Logger + can.Notifier."""
    msgs = reference_messages()
    done = threading.Event()
    count = 0

    class Count(can.Listener):
        def on_message_received(self, msg: can.Message) -> None:
            nonlocal count
            count += 1
            if count == len(msgs):
                done.set()

    with can.Bus(interface="virtual", channel="ref", receive_own_messages=False) as rx, \
            can.Bus(interface="virtual", channel="ref", preserve_timestamps=True) as tx:
        logger = can.Logger(str(path))
        notifier = can.Notifier(rx, [logger, Count()])
        try:
            for m in msgs:
                tx.send(m)
            if not done.wait(10.0):
                raise RuntimeError(f"only {count} of {len(msgs)} frames reached the logger")
        finally:
            notifier.stop()
            logger.stop()


def write_project_references() -> None:
    from benchmarks.can import msp25_samples
    from replay.can.logs import CanLogSink

    samples = msp25_samples(0.05, seed=0)
    for suf in (".asc", ".blf", ".log", ".trc"):
        with CanLogSink(HERE / f"msp25_short{suf}") as sink:
            sink.write(samples)


def main() -> None:
    for suf in (".log", ".asc"):
        record_with_python_can(HERE / f"msp25_pycan_reference{suf}")
    write_project_references()


if __name__ == "__main__":
    main()
