"""The Foxglove layout of the live view (``deploy/foxglove-layout.json``; ``python -m twin.service.live_view
--layout FILE`` writes it)."""

from __future__ import annotations

import json

from twin.models import DEFAULT_MODEL
from twin.reports.units import Shown, pretty_unit, signal_unit

from twin.service.live_view.messages import EXAMPLE_RIG

PARAMETERS = ("Ffric", "CdAleak", "Cd", "zeta", "wn")


def _plot(title: str, series: list[tuple[str, str, str]], *, ylabel: str = "") -> dict:
    return {"title": title, "paths": [{"value": v, "enabled": True, "timestampMethod": "receiveTime", "label": lbl,
                                       "color": c} for v, lbl, c in series],
            "showXAxisLabels": True, "showYAxisLabels": True, "showLegend": True, "legendDisplay": "floating",
            "showPlotValuesInLegend": True, "isSynced": True, "xAxisVal": "timestamp", "followingViewWidth": 120,
            "sidebarDimension": 240, **({"yAxisLabel": ylabel} if ylabel else {})}


def foxglove_layout(parameters=PARAMETERS, model: str = DEFAULT_MODEL, rig: str = EXAMPLE_RIG) -> dict:
    """The Foxglove layout of the live view (``deploy/foxglove-layout.json``): per parameter its estimate,
    95 % interval and healthy band over time (the ``display`` numbers of each parameter, in the display units
    of ``twin params``, the unit in the title: ``wn [Hz]``, ``CdAleak [mm²]``); the time
    until each parameter leaves its band with its 90 % interval (``/twin/forecast``, seconds); the rig's
    position and pressures (the ``display`` numbers of ``/rig/signals``: mm, MPa, the unit in the title; the
    messages carry SI); the alarms (Log panel) and the last status.
    The variable ``rig`` selects the rig shown (default: the first rig of ``deploy/rigs.example.toml``)."""
    sel = "{rig==$rig}"
    config: dict = {}
    plots = []
    for i, name in enumerate(parameters):
        sh = Shown(name, model)
        base = f"/twin/estimate{sel}.params.{name}.display"
        pid = f"Plot!param{i}"
        config[pid] = _plot(sh.label, [
            (f"{base}.value", "estimate", "#0072BD"), (f"{base}.lo95", "95 % low", "#4DBEEE"),
            (f"{base}.hi95", "95 % high", "#4DBEEE"), (f"{base}.band_lo", "band low", "#77AC30"),
            (f"{base}.band_hi", "band high", "#77AC30")])
        plots.append(pid)
    colors = ("#0072BD", "#D95319", "#EDB120", "#7E2F8E", "#77AC30", "#4DBEEE", "#A2142F")
    fc = f"/twin/forecast{sel}.forecasts"
    series = []
    for i, name in enumerate(parameters):
        c = colors[i % len(colors)]
        series += [(f"{fc}.{name}.remaining_s", f"{name} median", c),
                   (f"{fc}.{name}.remaining_lo_s", f"{name} 5 %", c), (f"{fc}.{name}.remaining_hi_s", f"{name} 95 %", c)]
    config["Plot!forecast"] = _plot("time until each parameter leaves its band, median and 90 % interval [s]",
                                    series, ylabel="remaining time [s]")
    sig = f"/rig/signals{sel}.display"
    own = _model_signals(model)
    signal_plots = []
    if "x" in own:
        x_unit = pretty_unit(signal_unit("x", model)[0])
        config["Plot!position"] = _plot(f"position x, demand x_ref [{x_unit}]", [
            (f"{sig}.{n}", n, c) for n, c in (("x", "#0072BD"), ("x_ref", "#8c8c8c")) if n in own])
        signal_plots.append("Plot!position")
    if "pA" in own:
        p_unit = pretty_unit(signal_unit("pA", model)[0])
        config["Plot!pressures"] = _plot(f"chamber pressures [{p_unit}]", [
            (f"{sig}.{n}", n, c) for n, c in (("pA", "#D95319"), ("pB", "#7E2F8E")) if n in own])
        signal_plots.append("Plot!pressures")
    if not signal_plots:  # a model of other signals (a force u and a displacement y): one plot of them all
        config["Plot!signals"] = _plot(
            "signals [" + ", ".join(f"{n} {pretty_unit(signal_unit(n, model)[0])}" for n in own) + "]",
            [(f"{sig}.{n}", n, colors[i % len(colors)]) for i, n in enumerate(own)])
        signal_plots.append("Plot!signals")
    config["Log!alarms"] = {"searchTerms": [], "minLogLevel": 1, "topicToRender": "/twin/alarm_log",
                            "nameFilter": {}, "fontSize": 12}
    config["RawMessages!status"] = {"topicPath": f"/twin/status{sel}", "diffEnabled": False, "diffMethod": "custom",
                                    "diffTopicPath": "", "showFullMessageForDiff": False, "expansion": "all"}

    def stack(ids: list[str], direction: str = "column"):
        if len(ids) == 1:
            return ids[0]
        return {"first": ids[0], "second": stack(ids[1:], direction), "direction": direction,
                "splitPercentage": 100.0 / len(ids)}

    layout = {"first": stack(plots), "second": {
        "first": stack(["Plot!forecast", *signal_plots]),
        "second": {"first": "Log!alarms", "second": "RawMessages!status", "direction": "column",
                   "splitPercentage": 60},
        "direction": "column", "splitPercentage": 50}, "direction": "row", "splitPercentage": 55}
    return {"configById": config, "globalVariables": {"rig": rig}, "userNodes": {}, "playbackConfig": {"speed": 1},
            "layout": layout}


def _model_signals(model: str) -> tuple[str, ...]:
    """The signals ``model``'s records carry (its ``SIGNALS``; the rig's five when it does not say)."""
    try:
        from twin.models import get_model

        return tuple(s.name for s in get_model(model).SIGNALS)
    except Exception:  # a model name the registry does not know: the hydraulic rig's signals
        return ("x_ref", "u", "x", "pA", "pB")


def write_layout(path: str, rig: str = EXAMPLE_RIG, model: str = DEFAULT_MODEL) -> str:
    """Write :func:`foxglove_layout` as JSON (``python -m twin.service.live_view --layout deploy/foxglove-layout.json``)."""
    with open(path, "w", encoding="utf-8") as f:
        json.dump(foxglove_layout(model=model, rig=rig), f, indent=2, ensure_ascii=False)
        f.write("\n")
    return path
