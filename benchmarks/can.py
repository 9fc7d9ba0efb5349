"""CAN ingest benchmark: vectorised decode + alignment against a per-frame cantools loop.

``run()`` builds MSP25 traffic (seeded), then, in one run on the same frames, times

* ``vectorised``: :class:`replay.can.decode.FrameDecoder` (checks + DBC-driven numpy decode)
  and :class:`replay.can.decode.Aligner` over numpy frame blocks, in frames/s;
* ``cantools``: a plain loop ``db.decode_message(id, data)`` per frame (decode only,
  no checks, no alignment), in frames/s;

and their ratio; plus, for information, reading the same traffic from each log
format through python-can's readers (the file parsing dominates there).  Run as
``python -m benchmarks.can [--seconds 60]``.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from replay.base import ReadReport, Samples
from replay.can.decode import CanStream, make_plan
from replay.can.logs import FORMATS
from replay.can.encode import FrameScheduler
from replay.can.logs import CanLogSink, CanLogSource
from replay.can.codec import Frames, VectorCodec


def msp25_samples(seconds: float, seed: int = 0, rate_hz: float = 1000.0,
                  t0_ns: int = 1_700_000_000_000_000_000) -> Samples:
    """Seeded, plausible MSP25 signals (SI units) on a ``rate_hz`` grid."""
    rng = np.random.default_rng(seed)
    n = int(round(seconds * rate_hz))
    t = np.arange(n) / rate_hz
    x_ref = 0.02 * np.sin(2 * np.pi * 1.0 * t)
    x = x_ref + 2e-5 * rng.standard_normal(n)
    return Samples(t0_ns + np.round(t * 1e9).astype(np.int64), {
        "x_ref": x_ref, "x": x,
        "u": np.clip(400.0 * (x_ref - x) + 2.0 * np.cos(2 * np.pi * t), -10, 10),
        "pA": 10e6 + 2e6 * np.sin(2 * np.pi * t) + 1e4 * rng.standard_normal(n),
        "pB": 10e6 - 2e6 * np.sin(2 * np.pi * t) + 1e4 * rng.standard_normal(n),
        "pP": np.full(n, 21e6), "T_oil": 318.15 + 0.01 * t,
    })


def msp25_frames(seconds: float, seed: int = 0, codec: VectorCodec | None = None) -> Frames:
    """The frames the MSP25 controller and HPU would send for ``seconds`` of the signals above."""
    codec = codec or VectorCodec()
    return FrameScheduler(codec, decimate=True).frames(msp25_samples(seconds, seed))


def _best(f, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        f()
        best = min(best, time.perf_counter() - t)
    return best


def run(seconds: float = 60.0, repeat: int = 3, formats: bool = True, block: int = 65536) -> dict:
    """Frames/s of the vectorised path and of a per-frame cantools loop on the same frames."""
    codec = VectorCodec()
    fr = msp25_frames(seconds, codec=codec)
    n = len(fr)
    plan = make_plan(codec, None, None)

    def vectorised() -> None:
        stream = CanStream(codec, plan, ReadReport("bench"))
        out = 0
        for a in range(0, n, block):
            out += len(stream.feed(fr.take(slice(a, a + block))))
        out += len(stream.flush())

    db = codec.db
    ids = (fr.key & 0x1FFF_FFFF).tolist()
    payload = [bytes(r[:d]) for r, d in zip(fr.data, fr.dlc.tolist())]

    def per_frame() -> None:
        dec = db.decode_message
        for i, d in zip(ids, payload):
            dec(i, d, decode_choices=False)

    t_vec = _best(vectorised, repeat)
    t_ct = _best(per_frame, max(1, repeat - 1))
    out: dict[str, Any] = {
        "frames": n, "log_seconds": seconds,
        "vectorised_frames_per_s": n / t_vec,
        "cantools_frames_per_s": n / t_ct,
        "ratio": t_ct / t_vec,
        "vectorised_x_real_time": seconds / t_vec,
    }
    if formats:
        samples = msp25_samples(min(seconds, 20.0))
        with tempfile.TemporaryDirectory() as d:
            rates = {}
            for suf in FORMATS:
                p = Path(d) / f"bench{suf}"
                with CanLogSink(p) as sink:
                    sink.write(samples)
                    nf = sink.frames_out
                t = time.perf_counter()
                with CanLogSource(p) as src:
                    src.read_all()
                rates[suf[1:]] = nf / (time.perf_counter() - t)
            out["file_read_frames_per_s"] = rates
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.can", description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="log seconds of MSP25 traffic (default 60)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-formats", action="store_true", help="skip the per-format file read figures")
    args = ap.parse_args(argv)
    res = run(args.seconds, args.repeat, formats=not args.no_formats)
    print(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
