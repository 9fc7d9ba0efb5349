"""Early warning (:mod:`twin.online.forecast`): when each parameter leaves its band, with a 90 % interval.

Synthetic streams check the model where its answer is known (a flat parameter has no forecast, a straight
wear is forecast to its exit, a checkpoint continues exactly, a reset forgets); a short record of the
independent reference simulator with a fast leakage wear goes through ``twin track`` (JSON, MCAP, report)
and through a checkpoint and restart of the rig's twin with a real alarm journal.
"""

from __future__ import annotations

import json
import math
import pickle

import numpy as np
import pytest
from mcap.reader import make_reader

from twin import cli
from twin.online.baseline import Baseline
from twin.online.forecast import DISCREPANCY, ForecastMonitor, discrepancy_of
from twin.online.events.forecast import FORECAST_SCHEMA, describe
from twin.online.events import AlarmEvent, validate
from twin.service.checkpoint_file import decode_state, encode_state

RATE = 20.0  # samples per second of the synthetic streams
BASE = {"CdAleak": Baseline(1.0, 1.0 / 3.0, 3.0), "wn": Baseline(1.0, 1.0 / 1.15, 1.15)}


def _ar1(rng: np.random.Generator, n: int, sd: float, tau: float) -> np.ndarray:
    """AR(1) noise of standard deviation ``sd`` and correlation time ``tau`` [s] at RATE (the filter's memory)."""
    a = math.exp(-1.0 / (RATE * tau))
    e = rng.normal(0.0, sd * math.sqrt(1 - a * a), n)
    out = np.empty(n)
    x = rng.normal(0.0, sd)
    for i in range(n):
        x = a * x + e[i]
        out[i] = x
    return out


def _stream(seed: int, seconds: float, leak, wn=None, sd=(0.05, 0.004)):
    """(t_ns, t_s, estimates, log stds, frozen) of a tracked CdAleak and wn whose truths are ``leak(t)``,
    ``wn(t)`` (relative to the baseline), estimated with AR(1) errors in log coordinates."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1.0 / RATE)
    truth = np.stack([leak(t), np.ones_like(t) if wn is None else wn(t)], axis=1)
    err = np.stack([_ar1(rng, t.size, sd[0], 0.5), _ar1(rng, t.size, sd[1], 0.5)], axis=1)
    est = truth * np.exp(err)
    ls = np.tile(np.array(sd, float), (t.size, 1))
    return (1_700_000_000_000_000_000 + np.round(t * 1e9).astype(np.int64), t, est, ls,
            np.zeros(est.shape, bool))


def _feed(fm: ForecastMonitor, stream, lo: int = 0, hi: int | None = None, block: int = 997):
    t_ns, t, est, ls, fr = stream
    hi = len(t) if hi is None else hi
    events, fcs = [], []
    for i in range(lo, hi, block):
        j = min(hi, i + block)
        e, f = fm.update_block(("CdAleak", "wn"), t_ns[i:j], t[i:j], est[i:j], ls[i:j], fr[i:j])
        events += e
        fcs += f
    return events, fcs


def test_a_flat_parameter_has_no_forecast_and_raises_nothing():
    # 40 min of a healthy rig: both parameters hold still; the filter's errors are correlated over 0.5 s
    stream = _stream(1001, 2400.0, lambda t: np.full_like(t, 1.4), lambda t: np.full_like(t, 0.95))
    fm = ForecastMonitor("r", BASE)
    events, fcs = _feed(fm, stream)
    assert events == []
    assert fcs == [] and fm.latest() == {}


def test_a_minute_of_a_slowly_forgetting_estimate_is_not_read_as_a_trend():
    """40 flat leakages whose estimates wander as the filter's memory makes them (AR(1) of scatter 0.3 with the
    time constant ``V / q`` of a stated log std of 0.37 and the spec's drift rate 0.15: about 6 s), 4 min each:
    over the first minutes a few excursions look like a trend to the residuals' own autocorrelation time, not to
    the filter's memory, which the forecast takes as the least correlation of its bins."""
    rate, sd_stated = 0.15, 0.37
    tau = sd_stated ** 2 / rate ** 2
    t = np.arange(0.0, 240.0, 1.0 / RATE)
    t_ns = 1_700_000_000_000_000_000 + np.round(t * 1e9).astype(np.int64)
    base = {"CdAleak": BASE["CdAleak"]}

    def feed(fm, seed):
        est = np.exp(_ar1(np.random.default_rng(seed), t.size, 0.3, tau))[:, None]
        ls = np.full((t.size, 1), sd_stated)
        raised, n_fc = 0, 0
        for i in range(0, t.size, 997):
            j = min(t.size, i + 997)
            e, f = fm.update_block(("CdAleak",), t_ns[i:j], t[i:j], est[i:j], ls[i:j], np.zeros((j - i, 1), bool))
            raised += sum(1 for a in e if a.kind == "raised")
            n_fc += len(f)
        return raised, n_fc

    floor = [feed(ForecastMonitor("r", base, horizon_s=600.0), 2000 + k) for k in range(40)]
    # a drift rate so fast that the filter's memory is far shorter than a bin: Geyer's estimate alone
    plain = [feed(ForecastMonitor("r", base, horizon_s=600.0, drift_rate={"CdAleak": 100.0}), 2000 + k)
             for k in range(40)]
    raised_floor = sum(1 for r, _ in floor if r)
    raised_plain = sum(1 for r, _ in plain if r)
    assert raised_floor <= 1 and raised_plain >= 4 * max(raised_floor, 1)
    assert sum(n for _, n in floor) < 0.25 * sum(n for _, n in plain)


def test_a_straight_wear_is_forecast_to_its_exit_with_one_early_alarm():
    # the leakage grows linearly from 1.2 to 3.6 over 20 min: it leaves its band (hi 3.0) at 900 s
    def leak(t):
        return 1.2 + 2.4 * t / 1200.0

    stream = _stream(1002, 1200.0, leak)
    fm = ForecastMonitor("r", BASE, horizon_s=600.0)
    events, fcs = _feed(fm, stream)
    exit_t = 900.0
    leak_fc = [f for f in fcs if f.parameter == "CdAleak"]
    assert all(f.parameter == "CdAleak" for f in fcs)  # none on the flat wn
    ts = [f.t for f in leak_fc]
    assert ts == sorted(ts) and np.allclose(np.diff(ts), 1.0, atol=0.06)  # one per second once it exists
    last_third = [f for f in leak_fc if exit_t - 900.0 / 3 <= f.t < exit_t]
    assert len(last_third) >= 290
    covered = [f.t_exit_lo is not None and f.t_exit_lo <= exit_t <= (f.t_exit_hi or math.inf) for f in last_third]
    assert 0.8 <= np.mean(covered) <= 1.0
    assert all(f.edge == "high" for f in last_third)
    raised = [e for e in events if e.level == "early"]
    assert len(raised) == 1 and raised[0].kind == "raised" and raised[0].parameter == "CdAleak"
    # with a 10-minute horizon it is raised when the exit is about 10 minutes away, not at the first trend
    assert exit_t - 600.0 - 120.0 <= raised[0].t_s <= exit_t - 900.0 / 4
    assert raised[0].message.startswith("CdAleak leaves its band in ") and " min [" in raised[0].message
    assert raised[0].statistic >= 0.9 and raised[0].band_hi == 3.0
    assert AlarmEvent.from_dict({**raised[0].to_dict(), "seq": 1}).level == "early"


def test_a_wear_that_starts_after_healthy_running_is_forecast_from_its_onset():
    """Ten healthy minutes, then the leakage grows linearly from 1.2 and leaves its band (hi 3.0) 450 s later: a
    straight line through all the data bends the evidence away (its residuals are one long excursion); the trend
    from a hinge where the wear starts finds it, forecasts the exit and warns a quarter of the wear ahead."""
    onset, exit_t = 600.0, 1050.0

    def leak(t):
        return 1.2 + 1.8 * np.clip(t - onset, 0.0, None) / (exit_t - onset)

    stream = _stream(1004, 1100.0, leak)
    fm = ForecastMonitor("r", BASE, horizon_s=600.0)
    events, fcs = _feed(fm, stream)
    leak_fc = [f for f in fcs if f.parameter == "CdAleak"]
    assert not [f for f in leak_fc if f.t < onset]  # nothing while it is flat
    last_third = [f for f in leak_fc if exit_t - (exit_t - onset) / 3 <= f.t < exit_t]
    assert len(last_third) >= 140
    covered = [f.t_exit_lo is not None and f.t_exit_lo <= exit_t <= (f.t_exit_hi or math.inf) for f in last_third]
    assert np.mean(covered) >= 0.8
    raised = [e for e in events if e.level == "early" and e.kind == "raised"]
    assert len(raised) == 1 and raised[0].parameter == "CdAleak"
    assert onset < raised[0].t_s <= exit_t - (exit_t - onset) / 4


def test_each_parameter_has_its_own_discrepancy_and_a_wider_one_widens_only_its_interval():
    """The slow level error is per parameter, a fraction of the bins' scatter (another model's parameter takes the
    largest; one number sets all); a larger one for the leakage widens the leakage's interval and leaves its
    median where it was, and the same fraction widens a noisier stream's interval more."""
    fm = ForecastMonitor("r", BASE)
    assert fm.discrepancy == {"CdAleak": DISCREPANCY["CdAleak"], "wn": DISCREPANCY["wn"]}
    assert all(0.0 < v < 1.0 for v in DISCREPANCY.values())  # slower than the bins' scatter, and smaller
    assert discrepancy_of(["k_other"]) == {"k_other": max(DISCREPANCY.values())}
    assert discrepancy_of(["CdAleak", "wn"], 0.01) == {"CdAleak": 0.01, "wn": 0.01}
    assert discrepancy_of(["CdAleak", "wn"], {"wn": 0.02})["wn"] == 0.02

    def leak(t):
        return 1.2 + 2.4 * t / 1200.0

    def widths(sd: float) -> tuple[float, float]:
        stream = _stream(1002, 800.0, leak, sd=(sd, 0.004))
        last = {}
        for d in (0.0, 1.0):
            fm = ForecastMonitor("r", BASE, horizon_s=600.0, discrepancy={"CdAleak": d})
            _, fcs = _feed(fm, stream)
            last[d] = [f for f in fcs if f.parameter == "CdAleak"][-1]
        narrow, wide = last[0.0], last[1.0]
        assert abs(wide.t_exit - narrow.t_exit) < 0.1 * (narrow.t_exit - narrow.t)
        return narrow.t_exit_hi - narrow.t_exit_lo, wide.t_exit_hi - wide.t_exit_lo

    quiet, noisy = widths(0.05), widths(0.15)
    assert quiet[1] > 1.5 * quiet[0]
    # the allowance follows the scatter (a fixed one would widen the noisy stream's interval by no more)
    assert noisy[1] - noisy[0] > 1.5 * (quiet[1] - quiet[0])


def test_state_is_plain_data_and_a_restored_monitor_continues_exactly():
    stream = _stream(1003, 900.0, lambda t: 1.0 + 2.5 * t / 900.0)
    whole = ForecastMonitor("r", BASE)
    ev_a, fc_a = _feed(whole, stream)
    first = ForecastMonitor("r", BASE)
    cut = 400 * int(RATE) + 7  # mid-bin
    ev_1, fc_1 = _feed(first, stream, 0, cut)
    # through the checkpoint file's own encoding (JSON text, the bins as raw bytes)
    state = decode_state(json.loads(json.dumps(encode_state(first.state()))))
    second = ForecastMonitor("r", BASE)
    second.restore(state)
    ev_2, fc_2 = _feed(second, stream, cut)
    assert [e.identity for e in ev_1 + ev_2] == [e.identity for e in ev_a] and ev_a
    assert [(f.parameter, f.t_ns) for f in fc_1 + fc_2] == [(f.parameter, f.t_ns) for f in fc_a]
    # the same numbers up to the rounding of a bin's sum split over two blocks
    got = np.array([(f.t_exit, f.t_exit_lo, f.t_exit_hi or 0.0, f.p_within_horizon) for f in fc_1 + fc_2])
    want = np.array([(f.t_exit, f.t_exit_lo, f.t_exit_hi or 0.0, f.p_within_horizon) for f in fc_a])
    assert np.allclose(got, want, rtol=1e-9, atol=1e-9)
    # a state written by an earlier version (the bins as lists of numbers) restores to the same point
    older = {**state, "params": {n: {**d, "points": d["points"].tolist()} for n, d in state["params"].items()}}
    third = ForecastMonitor("r", BASE)
    third.restore(json.loads(json.dumps(encode_state(older))))
    ev_3, fc_3 = _feed(third, stream, cut)
    assert [e.identity for e in ev_3] == [e.identity for e in ev_2]
    assert [(f.t_ns, f.t_exit) for f in fc_3] == [(f.t_ns, f.t_exit) for f in fc_2]


def test_the_history_goes_into_a_checkpoint_as_raw_bytes():
    """A full history (1800 bins of each parameter) is in every checkpoint, every second: its bins go in as one
    array (raw bytes), not as lists of numbers (which JSON writes digit by digit)."""
    stream = _stream(1005, 2000.0, lambda t: 1.0 + 1.5 * t / 2000.0)
    fm = ForecastMonitor("r", BASE)
    _feed(fm, stream)
    state = fm.state()
    pts = state["params"]["CdAleak"]["points"]
    assert isinstance(pts, np.ndarray) and pts.dtype == np.float64 and pts.shape[1] == 4 and len(pts) > 1000
    doc = json.dumps(encode_state(state))
    as_lists = json.dumps({**state, "params": {n: {**d, "points": d["points"].tolist()}
                                               for n, d in state["params"].items()}}, default=str)
    assert len(doc) < 0.6 * len(as_lists)
    back = decode_state(json.loads(doc))
    assert all(np.array_equal(back["params"][n]["points"], state["params"][n]["points"]) for n in BASE)


def test_a_maintenance_reset_forgets_the_history_and_returns_the_early_alarm():
    stream = _stream(1004, 600.0, lambda t: 1.0 + 2.5 * t / 700.0)
    fm = ForecastMonitor("r", BASE)
    events, _ = _feed(fm, stream)
    assert [e.level for e in events] == ["early"]
    back = fm.reset(["CdAleak"], why="seal replaced")
    assert [(e.level, e.kind, e.parameter) for e in back] == [("ok", "returned", "CdAleak")]
    assert "seal replaced" in back[0].message
    assert fm.latest() == {} and len(fm.state()["params"]["CdAleak"]["points"]) == 0


def test_the_message_gives_the_median_and_the_interval_in_one_unit():
    from twin.online.events.forecast import Forecast

    f = Forecast("CdAleak", 100.0, 0, 100.0 + 366.0, 100.0 + 240.0, 100.0 + 570.0, 0.95, 0.5, 20.0, "high")
    assert describe(f) == "in 6.1 min [4.0, 9.5]"


def test_a_bad_horizon_is_refused_in_one_line(tmp_path, capsys):
    rc = cli.main(["track", str(tmp_path / "missing.csv"), "--forecast-horizon", "-5"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc != 0 and len(err) == 1 and "--forecast-horizon" in err[0] and "Traceback" not in err[0]


# --- the reference simulator ---------------------------------------------------------------------------------------
WEAR_S, EXIT_S = 240.0, 180.0


@pytest.fixture(scope="module")
def wear_record():
    """240 s of the reference simulator (digital controller, 1 kHz, truth drawn within 10 % of Table 9): the
    leakage grows linearly from its drawn value and leaves its default band (3 x Table 9) at 180 s."""
    from conftest import get_records
    from reference import draw_truth, msp25_spec
    from reference.tables import MSP25_FREE

    truth = draw_truth(1101, 0.1, "msp25")
    v0, edge = truth["CdAleak"], 3.0 * MSP25_FREE["CdAleak"]
    end = v0 + (edge - v0) * WEAR_S / EXIT_S
    spec = msp25_spec(1101, duration=WEAR_S, truth=truth,
                      time_varying={"CdAleak": {"kind": "ramp", "t0": 0.0, "t1": WEAR_S, "start": v0, "end": end}})
    return get_records([spec], workers=1)[0]


@pytest.mark.slow
def test_twin_track_forecasts_a_wearing_seal_before_it_leaves_its_band(wear_record, tmp_path, capsys):
    log = tmp_path / "wear.csv"
    wear_record.to_csv(log)
    out = tmp_path / "out"
    assert cli.main(["track", str(log), "--out", str(out), "--json", "--forecast-horizon", "600",
                     "--maintenance", "CdAleak@200:seal replaced"]) == 0
    doc = json.loads(capsys.readouterr().out)
    fcs = doc["forecasts"]
    assert fcs and all(set(f) == {"parameter", "t", "t_exit", "t_exit_lo", "t_exit_hi", "p_within_horizon"}
                       for f in fcs)
    assert [f["t"] for f in fcs] == sorted(f["t"] for f in fcs)
    leak = [f for f in fcs if f["parameter"] == "CdAleak"]
    t = np.array([f["t"] for f in leak])
    assert np.all(np.diff(t) > 0.9) and np.all(np.diff(t) < 1.1)  # one per second of record
    true_exit = float(wear_record.t[np.argmax(wear_record.hidden["CdAleak"] > doc["alarms"][0]["band_hi"])])
    assert abs(true_exit - EXIT_S) < 1.0
    window = [f for f in leak if true_exit - true_exit / 3 <= f["t"] < true_exit]
    assert len(window) >= 50
    cover = np.mean([f["t_exit_lo"] <= true_exit <= (f["t_exit_hi"] or math.inf) for f in window])
    assert cover >= 0.8
    early = [a for a in doc["alarms"] if a["level"] == "early"]
    assert [a["parameter"] for a in early] == ["CdAleak"] and early[0]["kind"] == "raised"
    assert early[0]["t"] <= true_exit - EXIT_S / 4  # a quarter of the wear's duration ahead at least
    assert early[0]["seq"] < min(a["seq"] for a in doc["alarms"] if a["level"] in ("warning", "alarm"))
    assert "leaves its band in" in early[0]["message"]
    with open(doc["files"]["mcap"], "rb") as f:
        msgs = [json.loads(m.data) for _, ch, m in make_reader(f).iter_messages(topics=["/twin/forecast"])]
    assert len(msgs) == len({f["t"] for f in fcs})
    for m in msgs:
        validate(m, FORECAST_SCHEMA, "forecast")
    with open(doc["files"]["report"], encoding="utf-8") as f:
        html = f.read()
    assert "Early warning" in html and "first early alarm" in html
    # the maintenance recorded at 200 s: the standing early alarm returns naming it, the forecast starts afresh
    assert doc["maintenance"] == [{"parameters": ["CdAleak"], "t": 200.0, "note": "seal replaced"}]
    back = [a for a in doc["alarms"] if a["level"] == "ok" and a["kind"] == "returned" and a["parameter"] == "CdAleak"
            and "maintenance #1: seal replaced" in a["message"]]
    assert len(back) == 1 and abs(back[0]["t"] - 200.0) <= 1.0
    assert not [f for f in leak if f["t"] >= 200.0]  # none within the settling time and least span after it
    assert "maintenance at 200 s: CdAleak (seal replaced)" in html


@pytest.mark.slow
def test_a_rig_restarted_from_an_older_checkpoint_journals_each_early_alarm_once(wear_record, tmp_path):
    """Checkpoint 20 s before the early alarm of an uninterrupted run, carry on to 40 s after it (its alarms
    journaled), die; restart from the checkpoint and finish: the journal holds exactly the alarms of one
    uninterrupted run, the early one among them."""
    from twin.service.journal import AlarmJournal
    from twin.service.rig import RigTwin
    from twin.service.track import SequenceNumbers, track
    from twin.service.config import RigConfig
    from twin.online.baseline import default_baseline

    samples = _samples(wear_record)
    reference = track(samples, "rig-f", forecast_horizon_s=600.0).alarms
    t_early = next(a.t_s for a in reference if a.level == "early")
    assert 20.0 < t_early < WEAR_S - 40.0

    class Journaled(SequenceNumbers):
        def __init__(self, journal):
            super().__init__()
            self.journal = journal

        def publish_alarm(self, ev):
            r = self.journal.record(ev)
            return r.event if r.new else None

    tracked = ("Ffric", "CdAleak", "Cd", "zeta", "wn")
    rig = RigConfig("rig-f", "msp25", "<test>", None, 0.0, tracked, {}, default_baseline("msp25", None, tracked),
                    forecast_horizon_s=600.0)
    n = len(samples)
    cut, die = int(n * (t_early - 20.0) / WEAR_S), int(n * (t_early + 40.0) / WEAR_S)
    with AlarmJournal(tmp_path / "rig-f.db") as journal:
        first = RigTwin(rig, Journaled(journal))
        for i in range(0, cut, 10000):
            first.write(samples.slice(i, min(cut, i + 10000)))
        checkpoint = pickle.dumps(first.state())
        for i in range(cut, die, 10000):
            first.write(samples.slice(i, min(die, i + 10000)))
        second = RigTwin(rig, Journaled(journal))
        second.restore(pickle.loads(checkpoint))
        for i in range(cut, n, 10000):
            second.write(samples.slice(i, min(n, i + 10000)))
        got = list(journal)
    assert second.stats.duplicates >= 1  # the early alarm was raised again after the restart, not journaled
    assert [(a.seq, a.identity) for a in got] == [(i + 1, a.identity) for i, a in enumerate(reference)]


def _samples(rec):
    from replay.base import Samples

    t_ns = 1_700_000_000_000_000_000 + np.round(rec.t * 1e9).astype(np.int64)
    return Samples(t_ns, {k: np.asarray(v, float) for k, v in rec.signals.items()})


def test_a_recorded_maintenance_is_kept_in_the_state_and_its_log_is_read_once_and_whole(tmp_path):
    from fpdd.errors import DataError
    from twin.service.maintenance import MaintenanceLog, check_request, maintenance_path

    stream = _stream(1005, 600.0, lambda t: 1.0 + 2.5 * t / 700.0)
    fm = ForecastMonitor("r", BASE)
    _feed(fm, stream)
    path = maintenance_path(tmp_path, "r")
    log = MaintenanceLog(path, "r")
    ev = log.append(*check_request({"parameters": "CdAleak", "note": "seal replaced"}, ("CdAleak", "wn")))
    assert ev["seq"] == 1 and ev["parameters"] == ["CdAleak"]
    with open(path, "ab") as f:  # a line being written by the service, not complete yet
        f.write(b'{"rig": "r", "seq": 2, "param')
    reader = MaintenanceLog(path, "r")
    assert reader.since(0) == [ev]
    back = fm.reset(ev["parameters"], why=ev["note"], record=ev)
    assert [(e.level, e.kind) for e in back] == [("ok", "returned")]
    assert fm.maintenance_seq == 1 and fm.maintained["CdAleak"]["note"] == "seal replaced"
    assert fm.maintained["CdAleak"]["t"] == pytest.approx(599.95, abs=1.0)
    again = ForecastMonitor("r", BASE)
    again.restore(decode_state(json.loads(json.dumps(encode_state(fm.state())))))
    assert again.maintenance_seq == 1 and again.maintained == fm.maintained
    assert reader.since(again.maintenance_seq) == []
    for bad, field in (({"parameters": []}, "maintenance.parameters"), ({"parameters": ["Q"]}, "'Q' not tracked"),
                       ({"parameters": ["wn"], "note": "a\nb"}, "maintenance.note"), ([], "JSON object")):
        with pytest.raises(DataError, match=field):
            check_request(bad, ("CdAleak", "wn"))
