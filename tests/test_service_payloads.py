"""The estimate payloads a rig's twin writes straight from its numbers are the very text of the event path
(``event_to_json(EstimateEvent.of_tracker(...))``) and validate as ``EstimateEvent``; anything the schema
would refuse goes the event path."""

from __future__ import annotations

import json

import numpy as np

from twin.service.config import parse_config
from twin.online.events import EstimateEvent, event_to_json
from twin.service.rig import make_twin


def test_estimate_payloads_written_from_the_numbers_are_the_event_paths_text():
    rig = parse_config({"rig": [{"name": "rig-7.b", "source": "x.mcap"}]}, "rigs.toml").rigs[0]
    twin = make_twin(rig)
    tr = twin.tracker
    rng = np.random.default_rng(3)
    for k in range(200):
        vals = np.exp(rng.normal(0, 3, len(tr.tracked))) * rng.choice([1e-9, 1.0, 300.0])
        stds = np.abs(rng.normal(0, 1, len(tr.tracked))) * vals * rng.choice([0.0, 1e-3, 1.0])
        nis = float(rng.choice([np.nan, 0.0, rng.exponential(3.0), 1e300]))
        t_ns, t_s = int(rng.integers(0, 2**62)), float(rng.uniform(0, 1e6))
        status = str(rng.choice(["ok", "gated", "repaired_covariance"]))
        got = twin._estimate_json(t_ns, t_s, vals, stds, nis, status)
        want = event_to_json(EstimateEvent.of_tracker(rig.name, t_ns, t_s, tr.tracked, vals, stds, tr.units,
                                                      nis if np.isfinite(nis) else None, status, rig.baseline,
                                                      tr.displays))
        assert got == want, k
        assert EstimateEvent.from_dict(json.loads(got)).rig == "rig-7.b"
        for name, (unit, scale) in zip(tr.tracked, tr.displays):  # the display copy: SI x the spec's scale
            p = json.loads(got)["params"][name]
            assert p["display"]["unit"] == unit and p["display"]["value"] == p["value"] * scale
            assert p["display"]["lo95"] == p["lo95"] * scale and p["display"]["hi95"] == p["hi95"] * scale
    bad = np.ones(len(tr.tracked))
    assert twin._estimate_json(0, 0.0, bad * np.nan, bad, 1.0, "ok") is None
    assert twin._estimate_json(0, 0.0, bad, -bad, 1.0, "ok") is None
    assert twin._estimate_json(0, 0.0, bad, bad, -1.0, "ok") is None
