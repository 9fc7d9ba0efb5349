"""Early warning on the benchmark's verification records of the reference simulator (``benchmarks.forecast``).

Each record is simulated by the independent reference simulator (``tests/reference``, cached) and goes through
``twin track``'s library exactly as ``python -m benchmarks.forecast --set verify --seed N`` runs it; the figures
asserted are the early-warning table's of docs/results/forecast.md. A 10-min wear record and a 20-min healthy one cost minutes
(simulation and tracker; minutes more on a loaded machine): marked slow with a timeout of their own, CI runs them
(``pytest -m slow``).
"""

from __future__ import annotations

import pytest

from benchmarks import forecast as bench


def _record(which: str, seed: int):
    from conftest import get_records

    for row in bench.WEAR[which]:
        if row[4] == seed:
            return get_records([bench.wear_spec(row[1], row[2], row[3], row[4], row[5], t0=bench.wear_start(row))], workers=1)[0], row[1]
    for _label, kind, dur, s in bench.HEALTHY[which]:
        if s == seed:
            return bench.logged(get_records([bench.healthy_spec(kind, dur, s)], workers=1)[0], kind), None
    raise KeyError(seed)


@pytest.mark.slow
@pytest.mark.timeout(1800)
def test_a_warming_oil_raises_no_early_alarm():
    """Seed 1014, 20 min: the oil warms 20 K in 10 min (bulk modulus -12 %, leakage x 1.82 by the reference
    simulator's temperature laws, T_oil logged) and stays warm; a healthy rig: no early alarm on any parameter."""
    rec, _ = _record("verify", 1014)
    assert rec.hidden["B"][-1] / rec.hidden["B"][0] == pytest.approx(0.88, abs=0.005)
    twin = bench.run_record(rec)
    fig = bench.healthy_figures(rec, twin)
    assert fig["hours"] == pytest.approx(1200.0 / 3600.0, rel=1e-3)
    assert fig["early"] == 0, fig["early_parameters"]


@pytest.mark.slow
@pytest.mark.timeout(1800)
@pytest.mark.parametrize("seed", [1002, 1006, 1019])
def test_a_wear_record_is_forecast_a_quarter_of_its_wear_ahead(seed):
    """A verification wear record: the 90 % intervals of the last third before the true exit hold it in at least
    80 % of the forecasts, the first early alarm comes at least a quarter of the wear's duration before the exit,
    and no other parameter raises one. 1002: the exponential leakage wear at doubled noise (its early alarm came
    0.238 of the wear ahead while the reach was one span); 1006: the valve's bandwidth; 1019: friction wearing at
    doubled noise, where a minute of the leakage's wander raised an early alarm on the leakage before its bins'
    correlation was bounded by the filter's memory."""
    rec, param = _record("verify", seed)
    twin = bench.run_record(rec)
    fig = bench.wear_figures(rec, twin, param)
    assert fig["forecasts_in_window"] >= 0.9 * fig["window_s"]
    assert fig["coverage"] >= 0.8, fig
    assert fig["lead_fraction"] >= 0.25, fig
    assert fig["early_other"] == []
