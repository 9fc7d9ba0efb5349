"""One unit convention in every output: every command run on one short record, every output walked.

Machine outputs (``--json``, saved files, the MCAP messages, the Zenoh payloads) are SI with the unit named
beside each physical value; human outputs (console text, progress lines, HTML reports) show each value in the
display unit of ``twin params`` (wn in Hz, CdAleak in mm², pressures in MPa, x in mm), never a bare SI
magnitude such as ``1.72447e-08`` or ``wn 270.177``.

The rule for a JSON number (:func:`unitless`): it is a physical value with its unit beside it when

* its object has a ``"unit"`` key (``{"value", "unit"[, "std"]}``, a row with its unit), or
* an enclosing object has a sibling ``"<key>_unit"`` of the key that leads to it (``"mse"`` beside
  ``"mse_unit": {"x": "m^2", ...}``), or
* an enclosing object has a ``"units"`` map naming the key that leads to it (``{"x": 0.001, "pA": 1e7,
  "units": {"x": "m", "pA": "Pa"}}``, the live view's rig signals), or
* a key on its path names the unit (``time_s``, ``t_ns``, ``rate_hz``, ``fit_pct``, ``f_lo_hz``);

else it must be a count, a ratio, an index or a statistic, listed by name in :data:`DIMENSIONLESS`.
"""

from __future__ import annotations

import contextlib
import html as htmllib
import io
import json
import os
import re
import sys
import threading

import pytest

from twin import cli
from twin.reports.units import pretty_unit

sys.path.insert(0, os.path.dirname(__file__))

from net_helpers import free_port  # noqa: E402

#: a key ending so names its unit
UNIT_SUFFIX = re.compile(r"(^|_)(s|ns|ms|us|hz|pct|mm|mpa|v|k|sec|nsec)(_per_[a-z]+)?$", re.IGNORECASE)

#: numbers that are no physical quantity: counts, indices, ratios, statistics and probabilities (by their key)
DIMENSIONLESS = frozenset({
    # counts and indices
    "samples", "n", "n_obs", "n_par", "nfev", "status", "iteration", "start", "seq", "df", "lags", "order",
    "ar_order", "n_tests", "n_innovations", "raises", "records_read", "samples_out", "samples_lost", "seed", "messages",
    "blocks", "duplicates", "estimates", "statuses", "alarms", "forecasts", "received_by_subscriber", "level", "line",
    "term",  # an ownership term's number (fencing)
    "speed", "factor",  # a replay speed (x real time), a drift's factor
    # ratios and relative values
    "ratio", "power_ratio", "share", "excess", "nrmse", "r2", "r2_excess", "ar1", "holdout_fraction",
    "holdout_gain", "acf_band",
    # statistics, probabilities and noise-normalised figures
    "p", "p_adjusted", "p_effect", "p_min_bonferroni", "alpha", "z", "Q", "lm", "lr", "delta_aicc", "loglik", "aic",
    "aicc", "bic", "fpe", "cost", "final_cost", "weighted_sse", "weighted_excess", "innovations_ss", "nis",
    "p_within_horizon", "holdout_p_adjusted",
    "snr", "error_to_noise",  # a signal's or an error's RMS over the noise's
    "misplaced",  # the share of an effect's gain its shifted signature explains again
})
#: objects whose every number is dimensionless
DIMENSIONLESS_TREES = frozenset({
    "counters", "orders", "corr", "acf", "holdout_gain_interval", "nrmse", "excess",
    "xcorr",  # cross-correlations of residual and input: coefficients, their band, lags in samples
    "innovation_std",  # of the noise-normalised residuals
    "signature",  # the naming rule's regression on an effect's shifted signature: sums of noise-normalised squares
    "holdout_test",  # the held-out gain's test: relative gains, their interval, the HAC lag in samples
})


#: display units: in a machine output only inside a ``display`` block (beside the SI value)
NOT_SI = frozenset({"mm", "um", "µm", "mm^2", "mm²", "MPa", "kPa", "bar", "Hz", "kHz", "ms", "cm^3", "mm/s", "kN/mm",
                    "V/MPa", "degC", "°C"})


def unitless(doc, where: str, described: frozenset = frozenset(), si: bool = True) -> list[str]:
    """Paths of the numbers in ``doc`` that are neither beside a unit nor named dimensionless.

    ``described``: key paths (list indices left out) whose unit the message's schema names (an MCAP channel's
    JSON schema: ``"description": "measured rod displacement (LVDT), m"``).  With ``si``, a ``"unit"`` must be
    SI (:data:`NOT_SI`) outside a ``display`` block."""
    bad: list[str] = []

    def walk(obj, path: tuple, parents: tuple) -> None:
        if isinstance(obj, dict):
            for k, v in obj.items():
                walk(v, path + (k,), parents + (obj,))
        elif isinstance(obj, list):
            for i, v in enumerate(obj):
                walk(v, path + (i,), parents + (obj,))
        elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
            keys = [k for k in path if isinstance(k, str)]
            if tuple(keys) in described:
                return
            if parents and isinstance(parents[-1], dict) and "unit" in parents[-1]:
                unit = parents[-1]["unit"]
                if si and unit in NOT_SI and "display" not in keys:
                    bad.append(f"{where}: {'/'.join(str(k) for k in path)} in {unit!r}, not SI")
                return
            if keys and keys[-1] in DIMENSIONLESS or any(UNIT_SUFFIX.search(k) or "_pct_" in k or k in DIMENSIONLESS_TREES
                                                          for k in keys):
                return
            for depth in range(len(path)):
                anc, k = parents[depth], path[depth]
                if isinstance(anc, dict) and isinstance(k, str) and f"{k}_unit" in anc:
                    return
                units = anc.get("units") if isinstance(anc, dict) else None
                if isinstance(units, dict) and isinstance(k, str) and isinstance(units.get(k), str):
                    if si and units[k] in NOT_SI and "display" not in keys:
                        bad.append(f"{where}: {'/'.join(str(k) for k in path)} in {units[k]!r}, not SI")
                    return
            text = f"{where}: {'/'.join('#' if isinstance(k, int) else str(k) for k in path)}"
            if not any(b.startswith(text + " = ") for b in bad):  # one line per path (list indices as #)
                bad.append(f"{text} = {obj!r}")

    walk(doc, (), ())
    return bad


def _display_units() -> dict[str, tuple[str, str]]:
    """Parameter -> (SI unit, display unit) of every parameter shown in another unit than its SI one."""
    from twin.models import MODELS, get_model

    out = {}
    for name in MODELS:
        m = get_model(name)
        specs = list(m.params().specs) + [s for e in m.EFFECTS.values() for s in e.params]
        for s in specs:
            if s.display_unit and s.display_unit != s.unit:
                out.setdefault(s.name, (s.unit, s.display_unit))
    return out


NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:e[-+]?\d+)?(?![\d.])"
#: a statistic printed in scientific notation is no physical value: p-values, LM/LR, costs
STATISTIC_BEFORE = re.compile(r"(\bp(_Holm|_adj\w*| \(Holm\)| × probes)?|α|alpha|LM|LR|Q|cost|AIC\w*|BIC|FPE|"
                              r"dAICc|ΔAICc|share|NRMSE|ratio|correlation|relative std|HAC / textbook)"
                              r"[\s=:<>~]*$")
#: what may follow a number to name its unit (or a percentage)
UNIT_AFTER = re.compile(r"\s?[A-Za-zµ°%]")


def _units_and_unitless() -> tuple[set[str], set[str]]:
    """All display units (ASCII and pretty) and the names of the dimensionless parameters."""
    from twin.models import MODELS, get_model
    from twin.reports.units import SIGNALS, pretty_unit

    units, unitless_names = set(), set()
    for name in MODELS:
        m = get_model(name)
        for s in list(m.params().specs) + [s for e in m.EFFECTS.values() for s in e.params]:
            u = s.display_unit or s.unit
            if u in ("1", ""):
                unitless_names.add(s.name)
            else:
                units |= {u, pretty_unit(u)}
    units |= {u for u, _ in SIGNALS.values()} | {"N s/m", "N/m"}
    return units, unitless_names


def bare_si(text: str, where: str, tables: bool = True) -> list[str]:
    """Places in human text where a physical value is in SI rather than its display unit.

    * a number in scientific notation (exponent of 4 or more either way) with no unit after it, in a line
      with no display unit (a table row has its unit column) and no dimensionless parameter, not a statistic;
    * a number followed by an SI unit whose display unit differs (``rad/s``, ``m^2``, ``Pa``);
    * ``NAME=NUMBER`` without a unit, for a parameter shown in another unit than its SI one;
    * with ``tables``: ``NAME NUMBER NUMBER`` in a row with no display unit (a console table without units).
    """
    units, unitless_names = _units_and_unitless()
    bad = []
    for m in re.finditer(rf"(?<![\w.]){NUMBER}", text):
        tok = m.group(0)
        exp = re.search(r"e([-+]?\d+)$", tok)
        if not exp or abs(int(exp.group(1))) < 4 or UNIT_AFTER.match(text, m.end()):
            continue
        line_start = text.rfind("\n", 0, m.start()) + 1
        line_end = text.find("\n", m.end())
        line = text[line_start:line_end if line_end >= 0 else len(text)]
        words = set(re.split(r"[\s,;:=()\[\]]+", line))
        if STATISTIC_BEFORE.search(text[line_start:m.start()]) or words & units or words & unitless_names:
            continue
        bad.append(f"{where}: bare SI magnitude {tok!r} in {text[max(0, m.start() - 40):m.end() + 20]!r}")
    for m in re.finditer(rf"(?<![\w.])({NUMBER})\s*(rad/s|m\^2|m²|Pa|m\^3/s)(?![\w^²/])", text):
        bad.append(f"{where}: a value in SI {m.group(2)!r} where the display unit is meant: "
                   f"{text[max(0, m.start() - 30):m.end() + 10]!r}")
    for m in re.finditer(r"\bunit: (rad/s|m\^2|m²|Pa|m\^3|m³)(?![\w^²³/])", text):  # a table's unit column
        bad.append(f"{where}: a table column in SI {m.group(1)!r}: {text[max(0, m.start() - 60):m.end()]!r}")
    unit_next = "|".join(re.escape(u) for u in sorted(units, key=len, reverse=True))
    for name, (_, shown) in _display_units().items():
        sep = "[=:]" if tables else "="  # in a report's table `NAME: x` is a cell under the column NAME
        # the unit right after the value, or after its standard error (``wn = 43.0 ± 0.1 Hz``)
        for m in re.finditer(rf"(?<![\w/.-]){re.escape(name)}\s*{sep}\s*({NUMBER})"
                             rf"(?!(?:\s*±\s*{NUMBER})?\s*(?:{unit_next})(?![\w^]))", text):
            bad.append(f"{where}: {name} without its unit ({shown}): {text[m.start():m.end() + 12]!r}")
        if not tables:
            continue
        for m in re.finditer(rf"(?<![\w/.-]){re.escape(name)}\s+({NUMBER})\s+({NUMBER})", text):
            line_end = text.find("\n", m.end())
            rest = set(re.split(r"\s+", text[m.end():line_end if line_end >= 0 else len(text)]))
            if not rest & {shown, pretty_unit(shown)}:
                bad.append(f"{where}: {name} shown as bare numbers (display unit {shown}): "
                           f"{text[m.start():m.end() + 12]!r}")
    return bad


def _table_lines(m: re.Match) -> str:
    """A table as lines ``header: cell | header: cell ...`` (each cell read under its column's header)."""
    rows = re.findall(r"<tr\b[^>]*>(.*?)</tr>", m.group(0), flags=re.S)
    if not rows:
        return ""
    cells = [[re.sub(r"<[^>]+>", " ", c).strip() for c in re.findall(r"<t[hd]\b[^>]*>(.*?)</t[hd]>", r, flags=re.S)]
             for r in rows]
    head = cells[0]
    return "\n" + "\n".join(" | ".join(f"{h}: {c}" for h, c in zip(head, row)) for row in cells[1:]) + "\n"


def html_text(path: str) -> str:
    """The visible text of an HTML report (tags, scripts, styles and embedded images removed); a table's cells
    are read under their column's header (``p (Holm): <1e-300``, ``estimate: 43.1 | unit: Hz``)."""
    with open(path, encoding="utf-8") as f:
        page = f.read()
    page = re.sub(r"<(script|style)\b.*?</\1>", " ", page, flags=re.S | re.I)
    page = re.sub(r"<table\b.*?</table>", _table_lines, page, flags=re.S | re.I)
    page = re.sub(r"</(tr|p|h\d|li|figcaption|div)>|<br\s*/?>", "\n", page, flags=re.I)  # a row, a line
    page = re.sub(r"<[^>]+>", " ", page)
    return htmllib.unescape(page)


# --- running every command in-process on one record ---------------------------------------------------------
def run(*argv: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main(list(argv))
    return rc, out.getvalue(), err.getvalue()


def replay(*argv: str) -> tuple[int, str, str]:
    from replay import cli as replay_cli

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            rc = replay_cli.main(list(argv))
        except SystemExit as exc:  # argparse
            rc = int(exc.code or 0)
    return rc, out.getvalue(), err.getvalue()


#: a schema's description naming a unit: "..., m", "sample time, s (log_time / 1e9)", "whole seconds (...)"
DESCRIBED_UNIT = re.compile(r"(,\s*[^\s,()]+(\s*\(.*\))?$)|\b(nano)?seconds\b")


def schema_described(schema: dict, prefix: tuple = ()) -> set[tuple]:
    """Key paths of a JSON schema whose description names the unit of the value."""
    out: set[tuple] = set()
    for key, prop in (schema.get("properties") or {}).items():
        if DESCRIBED_UNIT.search(str(prop.get("description", ""))):
            out.add(prefix + (key,))
        out |= schema_described(prop, prefix + (key,))
        if isinstance(prop.get("items"), dict):
            out |= schema_described(prop["items"], prefix + (key,))
    return out


def mcap_check(path: str, where: str) -> tuple[list[str], set[str]]:
    """Every JSON message of an MCAP file (read with the ``mcap`` library) through :func:`unitless`, with the
    units its channel's schema names; returns (what is unlabelled, the topics read)."""
    from mcap.reader import make_reader

    bad: list[str] = []
    topics: set[str] = set()
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            if channel.message_encoding != "json":
                continue
            topics.add(channel.topic)
            described = frozenset()
            if schema is not None and schema.encoding == "jsonschema":
                described = frozenset(schema_described(json.loads(schema.data)))
            for b in unitless(json.loads(message.data), f"{where} {channel.topic}", described):
                if b not in bad:
                    bad.append(b)
    return bad, topics


@pytest.fixture(scope="module")
def outputs(tmp_path_factory):
    """Every output of every command on one 1.5 s record: {name: text}, {name: JSON document}, {name: MCAP}."""
    d = tmp_path_factory.mktemp("walk")
    texts: dict[str, str] = {}
    docs: dict[str, object] = {}
    rec = str(d / "r.csv")

    def keep(name: str, res: tuple[int, str, str], json_out: bool = False) -> None:
        rc, out, err = res
        assert rc == 0, f"{name}: exit {rc}: {err[-2000:]}"
        texts[f"{name}{' --json' if json_out else ''} (stderr)"] = err
        if json_out:
            docs[f"{name} --json"] = json.loads(out)
        else:
            texts[f"{name} (stdout)"] = out

    # a record away from the defaults: a larger leak and a stiffer valve
    keep("simulate", run("simulate", "-o", rec, "--duration", "1.5", "--seed", "1000",
                         "--set", "CdAleak=0.006mm^2,wn=47Hz,Ffric=70N", "--json"), json_out=True)
    keep("simulate mcap", run("simulate", "-o", str(d / "r.mcap"), "--duration", "1.5", "--seed", "1001"))
    mcaps = {"simulate mcap": str(d / "r.mcap")}
    keep("params", run("params"))
    keep("params", run("params", "--json"), json_out=True)
    keep("params effects", run("params", "--effects", "laminar_leakage,sensor_delay"))
    fit_args = ["fit", rec, "--free", "Ffric,CdAleak,wn", "--start", "wn=40Hz"]
    keep("fit", run(*fit_args, "--save", str(d / "fit.json"), "--report", str(d / "fit")))
    keep("fit", run(*fit_args, "--json"), json_out=True)
    docs["fit --save"] = json.loads((d / "fit.json").read_text())
    texts["fit report"] = html_text(str(d / "fit" / "fit_report.html"))
    # the diagnosis on a record with a cause to name (a pressure sensor offset): its parameters, signature
    rec_e = str(d / "offset.csv")
    keep("simulate offset", run("simulate", "-o", rec_e, "--duration", "1.5", "--seed", "1002", "--effects",
                                "pressure_sensor_offset", "--set", "CdAleak=0.006mm^2,wn=47Hz,pA_off=0.2MPa"))
    diag_args = ["diagnose", rec_e, "--candidates", "laminar_leakage,pressure_sensor_offset", "--no-timing-test"]
    keep("diagnose", run(*diag_args, "--save", str(d / "diag.json"), "--report", str(d / "diag")))
    keep("diagnose", run(*diag_args, "--json"), json_out=True)
    docs["diagnose --save"] = json.loads((d / "diag.json").read_text())
    for name in ("diagnosis.json", "extended_params.json"):
        docs[f"diagnose --report {name}"] = json.loads((d / "diag" / name).read_text())
    texts["diagnose report"] = html_text(str(d / "diag" / "diagnose_report.html"))
    keep("track", run("track", rec, "--out", str(d / "track"), "--params", str(d / "fit.json")))
    keep("track", run("track", rec, "--out", str(d / "track"), "--params", str(d / "fit.json"), "--json"),
         json_out=True)
    texts["track report"] = html_text(str(d / "track" / "track_report.html"))
    mcaps["track mcap"] = str(d / "track" / "rig.twin.mcap")
    keep("paper", run("paper", "--case", "osc-A,rig-A-wn,rig-B", "--report", str(d / "paper")))
    keep("paper", run("paper", "--case", "rig-A-CdAleak", "--json"), json_out=True)
    texts["paper report"] = html_text(str(d / "paper" / "paper_report.html"))
    keep("replay info", replay("info", rec))
    keep("replay info", replay("info", "--json", rec), json_out=True)
    keep("replay info twin mcap", replay("info", str(d / "track" / "rig.twin.mcap")))
    keep("replay info twin mcap", replay("info", "--json", str(d / "track" / "rig.twin.mcap")), json_out=True)
    # twin serve for a few seconds on loopback Zenoh; a plain zenoh session takes every payload
    texts_z, docs_z = _serve(d, str(d / "r.mcap"))
    texts.update(texts_z)
    docs.update(docs_z)
    # the demo, short, with its leak alarm inside the record: console, summary, HTML alarm table, its MCAPs
    from twin.commands.demo import run as run_demo
    from twin.online.tracker import fmt_estimate

    lines: list[str] = []
    summary = run_demo(str(d / "demo"), duration_s=10.0, speed=0.0, seed=1000, t_start=1.0, t_end=6.0,
                       say=lines.append)
    assert summary["alarms"], "the demo raised no alarm: its alarm table is not walked"
    texts["demo (console)"] = "\n".join(lines + [fmt_estimate(n, v["value"], v["std"])
                                                 for n, v in summary["final"].items()])
    docs["demo --json"] = json.loads(json.dumps(summary, default=str))
    texts["demo report"] = html_text(summary["files"]["html"])
    mcaps["demo rig mcap"] = summary["files"]["rig_mcap"]
    mcaps["demo twin mcap"] = summary["files"]["twin_mcap"]
    # the live view: what a Foxglove client receives of these signals, estimates, statuses and alarms
    live, log_lines = _live_view(str(d / "r.mcap"), str(d / "track" / "rig.twin.mcap"), summary["alarms"])
    docs.update(live)
    texts["live view alarm log"] = "\n".join(log_lines)
    return texts, docs, mcaps


def _live_view(signals_mcap: str, twin_mcap: str, alarms: list[dict]) -> tuple[dict, list[str]]:
    from mcap.reader import make_reader

    from replay.factory import open_source
    from test_live_view import Client
    from twin.service.live_view import LiveView

    with open(twin_mcap, "rb") as f:
        msgs = [(ch.topic, json.loads(m.data)) for _, ch, m in make_reader(f).iter_messages()]
    estimates = [m for t, m in msgs if t == "/twin/estimate"][:3]
    statuses = [m for t, m in msgs if t == "/twin/status"][:1]
    assert estimates and statuses
    with open_source(signals_mcap) as src:
        block = next(iter(src.chunks()))
    with LiveView(port=0, signal_rate_hz=100.0) as view:
        client = Client(view.url)
        try:
            client.subscribe([t for t in client.channels if t != "/twin/forecast"])
            for topic in client.sub_of.values():
                assert view.wait_subscribed(topic, 30.0), topic
            sent = view.signals("rig-w", block)
            for e in estimates:
                view.estimate(dict(e, rig="rig-w"))
            for e in statuses:
                view.status(dict(e, rig="rig-w"))
            for a in alarms[:2]:
                view.alarm(a)
            got = client.messages({"/rig/signals": sent, "/twin/estimate": len(estimates), "/twin/status": 1,
                                   "/twin/alarm": min(2, len(alarms)), "/twin/alarm_log": min(2, len(alarms))},
                                  timeout=30.0)
        finally:
            client.close()
    docs = {f"live view {topic}": [m for _, m in got[topic]] for topic in got if topic != "/twin/alarm_log"}
    docs["live view /twin/alarm_log"] = [{k: v for k, v in m.items() if k != "message"}
                                         for _, m in got["/twin/alarm_log"]]
    return docs, [m["message"] for _, m in got["/twin/alarm_log"]]


def _serve(d, log: str) -> tuple[dict, dict]:
    import zenoh

    from fpdd.zenohconf import zenoh_config

    sub_port, svc_port = free_port(), free_port()
    cfg = d / "rigs.toml"
    cfg.write_text(f"""[zenoh]
mode = "peer"
listen = ["tcp/127.0.0.1:{svc_port}"]
connect = ["tcp/127.0.0.1:{sub_port}"]
[service]
journal_dir = "{d / 'journal'}"
estimate_every = 100
[[rig]]
name = "rig-w"
source = "{log}"
speed = 2.0
""", encoding="utf-8")
    got: list[tuple[str, bytes]] = []
    lock = threading.Lock()

    def take(sample) -> None:
        with lock:
            got.append((str(sample.key_expr), bytes(sample.payload.to_bytes())))

    with zenoh.open(zenoh_config("peer", listen=[f"tcp/127.0.0.1:{sub_port}"])) as session:
        sub = session.declare_subscriber("fpdd/**", take)
        try:
            rc, out, err = run("serve", "--config", str(cfg), "--json")
        finally:
            sub.undeclare()
    assert rc == 0, err[-2000:]
    payloads: dict[str, list] = {}
    for key, data in got:
        try:
            payloads.setdefault(key.split("/", 2)[-1], []).append(json.loads(data))
        except ValueError:  # a binary payload (signal blocks) carries its units in its schema
            continue
    assert any("estimate" in k for k in payloads), sorted(payloads)
    return {"serve (stderr)": err}, {"serve --json": json.loads(out), "serve zenoh": payloads}


# --- the checks ------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_every_machine_output_names_the_unit_of_each_physical_value(outputs):
    _, docs, mcaps = outputs
    assert {"fit --json", "fit --save", "diagnose --save", "diagnose --json", "track --json", "paper --json",
            "params --json", "simulate --json", "replay info --json", "serve zenoh"} <= set(docs)
    # the live view's payloads too: SI with the unit named, display units only under display (what the plots read)
    assert {"live view /rig/signals", "live view /twin/estimate", "live view /twin/alarm"} <= set(docs)
    bad = [b for name, doc in docs.items() for b in unitless(doc, name)]
    for name, path in mcaps.items():
        found, topics = mcap_check(path, name)
        assert topics, f"{name}: no JSON message in {path}"
        bad += found
    assert not bad, "numbers without a unit beside them:\n" + "\n".join(bad[:200])


def test_saved_parameters_are_si_values_with_units(outputs):
    _, docs, _ = outputs
    for name in ("fit --save", "diagnose --save"):
        params = docs[name]["params"]
        assert params["CdAleak"]["unit"] == "m^2" and params["wn"]["unit"] == "rad/s", name
        assert 1e-9 < params["CdAleak"]["value"] < 1e-7 and 200 < params["wn"]["value"] < 400, name
        assert params["wn"]["std"] > 0, name
    assert docs["fit --json"]["mse_unit"] == {"x": "m^2", "pA": "Pa^2", "pB": "Pa^2"}
    assert docs["simulate --json"]["params"]["CdAleak"]["value"] == pytest.approx(6e-9)


def test_every_human_output_is_in_the_display_units_of_twin_params(outputs):
    texts, _, _ = outputs
    assert {"fit (stdout)", "fit (stderr)", "diagnose (stdout)", "paper (stdout)", "fit report", "diagnose report",
            "track report", "paper report", "replay info (stdout)", "track (stdout)"} <= set(texts)
    # `twin params` defines the display units (a unit column beside value and bounds): checked below
    bad = [b for name, text in texts.items() if not name.startswith("params")
           for b in bare_si(text, name, tables=not name.endswith("report"))]
    assert not bad, "SI magnitudes in human outputs:\n" + "\n".join(bad[:200])
    # the display units are those of `twin params`, and they are there
    table = texts["params (stdout)"]
    for name, unit in (("wn", "Hz"), ("CdAleak", "mm^2"), ("pP", "MPa")):
        row = next(line for line in table.splitlines() if line.startswith(name + " "))
        assert f" {unit} " in row, row
    assert re.search(r"wn\s+4\d\.\d+ Hz", texts["fit (stdout)"])
    assert "CdAleak=" in texts["fit (stderr)"] and "mm^2" in texts["fit (stderr)"]
    assert re.search(r"rig-A-wn\s+wn\s+43\s", texts["paper (stdout)"])
    assert re.search(r"pA_off\s+0\.\d+ MPa \+/- [\d.]+ MPa", texts["diagnose (stdout)"])  # the cause, displayed
    assert "Signature of pressure_sensor_offset" in texts["diagnose report"]
    assert "MPa" in texts["replay info (stdout)"] and "mm" in texts["replay info (stdout)"]


def test_the_checks_catch_what_they_are_for():
    """The walkers themselves: each kind of bare value is caught, each kind of labelled value passes."""
    assert unitless({"mse": {"x": 1e-12}}, "d") and not unitless({"mse": {"x": 1e-12}, "mse_unit": {"x": "m^2"}}, "d")
    assert not unitless({"wn": {"value": 270.0, "unit": "rad/s"}, "time_s": 1.0, "nfev": 3}, "d")
    assert unitless({"wn": {"value": 43.0, "unit": "Hz"}}, "d")  # a machine output is SI
    assert not unitless({"wn": {"value": 270.0, "unit": "rad/s", "display": {"value": 43.0, "unit": "Hz"}}}, "d")
    assert unitless({"params": {"wn": 270.0}}, "d")
    signals = {"x": 1e-3, "pA": 1e7, "units": {"x": "m", "pA": "Pa"},
               "display": {"x": 1.0, "pA": 10.0, "units": {"x": "mm", "pA": "MPa"}}}
    assert not unitless(signals, "d") and not unitless([signals, signals], "d")
    assert unitless({"x": 1.0, "units": {"x": "mm"}}, "d")  # display units outside display: not SI
    assert unitless({"x": 1e-3, "pA": 1e7, "units": {"x": "m"}}, "d") == ["d: pA = 10000000.0"]
    assert unitless({"display": {"x": 1.0}}, "d")  # a display number needs its unit too
    assert bare_si("CdAleak 3.2863e-09", "t") and bare_si("start 0: wn=270.177 cost 3", "t")
    assert bare_si("rms 2.005e+04, noise floor 1.9e+04", "t") and bare_si("wn 270.177 270.17696 4e-06", "t")
    assert bare_si("A = 1.72447e-08 (alarm)", "t") and bare_si("final 3e-09 m^2", "t")
    assert bare_si("parameter: wn | estimate: 270.18 | unit: rad/s", "t", tables=False)
    assert not bare_si("parameter: wn | estimate: 43.001 | unit: Hz\np (Holm): <1e-300 | share: 2.5e-05", "t")
    assert not bare_si("wn=43.0051 Hz, CdAleak=0.0032863 mm^2, p_Holm=1e-30, p=2.5e-12", "t")
