"""Units by name: values with units on the way in (``wn=43Hz``, ``CdAleak=3.3mm^2``, ``Ffric=50N``, ``x=2um``),
and the display unit of a parameter or a signal of a model on the way out (:func:`param_spec`, :func:`signal_unit`,
which the estimation and the reports share).

The unit of a name is looked up among every model's parameters and the rig signals (:func:`known_units`; a
parameter's display unit: :func:`display_of`); the conversion is
:func:`fpdd.units.text_to_si` (pint, with ``Hz`` read as cycles per second for an angular frequency).
"""

from __future__ import annotations

import functools
import math

from fpdd.errors import ParameterError
from fpdd.units import SIGNAL_UNITS, SIGNALS, display, text_to_si

#: quantities shown beside the logged signals, not logged themselves: (display unit, factor from SI)
DERIVED_SIGNALS: dict[str, tuple[str, float]] = {"force": display("N"), "v": display("m/s")}


@functools.cache
def parameter_units() -> dict[str, tuple[str, str, float]]:
    """Parameter name -> (SI unit, display unit, display scale) over every model's parameters (the first model
    that names it wins)."""
    from twin.models import MODELS, get_model

    out: dict[str, tuple[str, str, float]] = {}
    for name in MODELS:
        for s in get_model(name).kernel_specs:
            out.setdefault(s.name, (s.unit, s.display_unit or s.unit, float(s.display_scale)))
    return out


@functools.cache
def known_units() -> dict[str, str]:
    """SI unit of every signal, and of every parameter name of every model."""
    out = dict(SIGNAL_UNITS)
    for name, (si, _, _) in parameter_units().items():
        out.setdefault(name, si)
    return out


def display_of(parameter: str, si_unit: str) -> tuple[str, float]:
    """``(display unit, scale)`` of a parameter known to the models with this SI unit (value in the display
    unit = SI value x scale, e.g. ``("Hz", 1/(2 pi))`` for ``wn``); ``(si_unit, 1.0)`` otherwise."""
    known = parameter_units().get(parameter)
    return (known[1], known[2]) if known is not None and known[0] == si_unit else (si_unit, 1.0)


def to_si(name: str, text: str, unit: str | None = None) -> float:
    """``text`` (a number, or a number with a unit) as a float in the SI unit of ``name``.

    ``unit``: the SI unit to convert to (default: looked up by ``name`` among the
    models' parameters and the signals).

    A bare number for a name whose display unit is not its SI unit (``wn``: Hz shown, rad/s inside;
    ``CdAleak``: mm^2 and m^2; ``pA``: MPa and Pa) is refused (:func:`bare_number`): it would be read in SI
    while people read the name in its display unit.  A value for a signal's name is a noise level (the one place
    a signal's name takes a value: ``--noise-levels``, ``[rig] noise``): it must lie within half the span of the
    signal's physical range (:func:`check_noise`), so ``x=2`` (2 m of noise) is refused.
    """
    try:
        value = float(text)
    except ValueError:  # a value with a unit: the models are asked for the unit of the name only then
        value = text_to_si(name, text, unit or known_units().get(name))
    else:
        value = text_to_si(name, text, unit)
        bare_number(name, value)
    if name in SIGNAL_UNITS and name not in parameter_units():
        check_noise(name, value, text)
    return value


def ambiguity(name: str) -> tuple[str, str, float] | None:
    """``(SI unit, display unit, display scale)`` of a name whose display unit differs from its SI unit (a bare
    number would be ambiguous), found from the parameters' declared display units (any model's) and the signals'
    display units; ``None`` when a bare number is unambiguous."""
    known = parameter_units().get(name)
    if known is not None:
        si, shown, scale = known
        return known if (shown != si or scale != 1.0) and si != "1" else None
    if name in SIGNAL_UNITS and "*" not in SIGNALS[name].accepts:  # a generic signal's unit follows the record
        si = SIGNAL_UNITS[name]
        shown, scale = display(si)
        return (si, shown, scale) if (shown != si or scale != 1.0) else None
    return None


def spelled(value: float, unit: str) -> str:
    """``value`` followed by ``unit`` as pint reads it back (``43Hz``, ``270.2rad/s``, ``0.0033mm^2``)."""
    return f"{value:.6g}{unit.replace(' ', '*')}"


def bare_number(name: str, value: float, *, unit: tuple[str, str, float] | None = None,
                assign: str = "{name}={value}") -> None:
    """Refuse (:class:`~fpdd.errors.ParameterError`, one line) a bare, non-zero ``value`` for ``name`` when its
    display unit differs from its SI unit; the message gives both spellings (``wn=43Hz`` or ``wn=43rad/s``,
    each with what it equals in the other unit).  ``unit``: ``(SI unit, display unit, display scale)`` when
    known (a parameter's spec), else :func:`ambiguity`.  ``assign``: how the hint writes a value (a format
    of ``name`` and ``value``; rigs.toml's is ``{name} = "{value}"``).  Zero is the same in every unit and passes."""
    unit = unit if unit is not None else ambiguity(name)
    if unit is None or value == 0.0:
        return
    si, shown, scale = unit
    if shown == si and scale == 1.0:
        return
    def put(v: str) -> str:
        return assign.format(name=name, value=v)

    raise ParameterError(
        f"{assign.format(name=name, value=f'{value:g}').replace(chr(34), '')}: a bare number is ambiguous ({name} is shown in {shown}, kept in {si}): write the "
        f"unit, {put(spelled(value, shown))} (= {spelled(value / scale, si)}) or {put(spelled(value, si))} "
        f"(= {spelled(value * scale, shown)})")


def physical_range(name: str, model: str | None = None) -> tuple[float, float] | None:
    """The physical range (SI) of signal ``name`` that ``model``'s records declare (the rig's table when no model
    is given); ``None`` for an unknown signal."""
    spec = None
    if model:
        from twin.models.records import signal_specs

        try:
            spec = signal_specs(model).get(name)
        except Exception:  # an unknown model: the rig's table
            spec = None
    spec = spec or SIGNALS.get(name)
    return (float(spec.lo), float(spec.hi)) if spec is not None else None


def check_noise(name: str, value: float, text: str | None = None, model: str | None = None) -> float:
    """Refuse a noise level (a standard deviation, SI) of signal ``name`` beyond half the span of the signal's
    physical range: no sensor's noise is wider than what the signal can read (a value confined to
    ``[lo, hi]`` has a standard deviation of at most ``(hi - lo) / 2``).  ``x=2`` is 2 m of noise on a
    displacement of +-0.5 m: the message names the range and how to write a unit."""
    rng = physical_range(name, model)
    if rng is None or not math.isfinite(value):
        return value
    lo, hi = rng
    limit = 0.5 * (hi - lo)
    if abs(value) > limit:
        si = SIGNAL_UNITS.get(name, "")
        shown, scale = display(si)
        given = f" (given as {text.strip()!r})" if text is not None else ""
        small = {"m": "um", "Pa": "kPa"}.get(si, si)
        raise ParameterError(
            f"{name}={value:g} {si}{given}: implausible noise level for {name}: its physical range "
            f"{lo * scale:g} .. {hi * scale:g} {shown} allows a standard deviation of at most {limit:g} {si}; "
            f"give the unit, e.g. {name}={spelled(abs(value), small)}")
    return value


def signal_unit(name: str, model: str | None = None) -> tuple[str, float]:
    """(display unit, factor from SI) of a logged signal of ``model``'s records
    (:func:`twin.models.records.signal_specs`: the oscillator's ``u`` is a force in N); SI and factor 1 when
    unknown."""
    from twin.models.records import signal_specs

    spec = signal_specs(model or "").get(name)
    return spec.display if spec is not None else DERIVED_SIGNALS.get(name, ("", 1.0))


@functools.cache
def _specs(model: str) -> dict:
    from twin.models import get_model

    m = get_model(model)
    out = {s.name: s for s in m.params().specs}
    for e in m.EFFECTS.values():
        for s in e.params:
            out.setdefault(s.name, s)
    return out


def param_spec(model: str | None, name: str):
    """The :class:`~twin.params.ParamSpec` of a parameter of ``model`` (effects included), or ``None``."""
    if not model:
        return None
    try:
        return _specs(model).get(name)
    except Exception:  # an unknown model name: shown in SI
        return None


def check_lengths(model, ps, signals, name: str = "record") -> None:
    """Refuse (:class:`~fpdd.errors.DataError`, one line) a length signal whose values lie beyond the rig's
    physical range (``model.filter_map(ps).ranges``: the position within the stroke) but within it read in mm:
    a column logged in mm read as metres.  The message names the peak, the range and the two ways to give the
    unit (``--map x=x:mm``, a header ``x[mm]``).  A model that declares no range is not checked.
    Within the range the rig's own loop tells (:func:`check_loop_scale`)."""
    import numpy as np

    from fpdd.errors import DataError

    check_loop_scale(ps, signals, name)
    try:
        ranges = dict(model.filter_map(ps).ranges)
    except Exception:  # a model the online twin does not run: no declared range
        return
    for sig, values in signals.items():
        spec = SIGNALS.get(sig)
        rng = ranges.get(sig, ranges.get("x") if sig == "x_ref" else None)
        if spec is None or spec.unit != "m" or "*" in spec.accepts or rng is None:
            continue
        v = np.asarray(values, dtype=np.float64)
        v = v[np.isfinite(v)]
        if not v.size:
            continue
        lo, hi = float(rng[0]), float(rng[1])
        peak_lo, peak_hi = float(v.min()), float(v.max())
        if lo <= peak_lo and peak_hi <= hi:
            continue
        if lo <= peak_lo * 1e-3 and peak_hi * 1e-3 <= hi:
            peak = peak_hi if abs(peak_hi) >= abs(peak_lo) else peak_lo
            raise DataError(
                f"{name}: {sig} reaches {peak:g} m, beyond the {model.name} rig's physical range {lo * 1e3:g} .. "
                f"{hi * 1e3:g} mm ({ps.spec('stroke').show(ps['stroke']) + ' stroke' if 'stroke' in ps else 'declared'}"
                f"): it reads like a column in mm ({peak:g} mm) read as metres; give its unit: --map {sig}={sig}:mm "
                f"or a header {sig}[mm] (a bare column is SI)")


#: How far (decades) a loop's scale may be from 1000 and still be read as a column in mm: a factor of 3 either way.
#: On the independent reference simulator (tests/reference, truth drawn, 4 s records, seeds 0-5: analog and digital
#: P, PI with KI 200, PD with KD 2, feed-forward 0.5, KP 250) the gain <u, e>/<e, e> is KP x 1.000 .. 1.157 (the
#: feed-forward's the largest) and x_ref/x 0.988 .. 1.003: a healthy record sits three decades from the refusal.
LOOP_SCALE_DECADES = 0.5


#: The level (two-sided normal quantile) at which a loop's scale must be determined before a refusal: 0.1 %.
LOOP_SCALE_Z = 3.29


def _scale_interval(r, x) -> tuple[float, float, float]:
    """The position per unit of demand ``b`` by least squares with the loop's lag, ``x = b x_ref + c x_ref' + e``
    (a loop follows its demand late: without the rate term a sweep's residual is the tracking error itself and the
    scale is lost in it), and its interval at :data:`LOOP_SCALE_Z` standard errors, the residual's autocorrelation
    counted (an AR(1)'s effective sample count).  A demand at rest leaves ``b`` undetermined: a wide interval, not
    a scale near 1/1000 by chance."""
    import numpy as np

    n = r.size
    X = np.column_stack([r, np.gradient(r)])
    G = X.T @ X
    if not (n > 3 and np.all(np.isfinite(G)) and np.linalg.cond(G) < 1e12):
        return float("nan"), float("nan"), float("nan")
    coef = np.linalg.solve(G, X.T @ x)
    e = x - X @ coef
    ee = float(np.dot(e, e))
    rho = float(np.dot(e[1:], e[:-1])) / ee if ee > 0 else 0.0
    rho = min(max(rho, 0.0), 0.999)
    var = float(np.linalg.inv(G)[0, 0]) * ee / (n - 2) * (1.0 + rho) / (1.0 - rho)
    b, se = float(coef[0]), float(np.sqrt(max(var, 0.0)))
    return b, b - LOOP_SCALE_Z * se, b + LOOP_SCALE_Z * se


def _loop_signals(signals, names=("x", "x_ref")):
    """The finite samples of ``names`` (each sample finite in all of them), or None when one is missing or fewer
    than 100 samples are left."""
    import numpy as np

    if any(n not in signals for n in names):
        return None
    arrays = [np.asarray(signals[n], dtype=np.float64) for n in names]
    ok = np.logical_and.reduce([np.isfinite(a) for a in arrays])
    if ok.sum() < 100:
        return None
    return [a[ok] for a in arrays]


def loop_scale_settled(signals) -> bool:
    """True when ``x`` and ``x_ref`` share one scale beyond doubt: the interval of :func:`_scale_interval` lies
    wholly outside both refusal bands (more data cannot refuse them any more), or the record has no demand."""
    import numpy as np

    if "x" not in signals or "x_ref" not in signals:
        return True
    both = _loop_signals(signals)
    if both is None:
        return False
    _, lo, hi = _scale_interval(both[1], both[0])
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return False
    far = 10.0 ** LOOP_SCALE_DECADES
    return bool(1e-3 * far < lo and hi < 1e3 / far)


def check_loop_scale(ps, signals, name: str = "record") -> None:
    """Refuse (:class:`~fpdd.errors.DataError`, one line) a position in mm read as metres whose values stay inside
    the stroke, which no range can tell: in closed loop the demand ``x_ref`` and the measured ``x`` share one scale,
    and the controller's drive is ``u = KP (x_ref - x)`` (``KP`` of ``ps``). With ``x`` and ``x_ref`` in the record,
    the least-squares scale of ``x`` on ``x_ref`` (its lag taken out) near 1000 (or 1/1000), its whole interval at
    the 0.1 % level (:func:`_scale_interval`), names ``x`` (or ``x_ref``): a demand at rest or a position lagging it leaves the
    scale undetermined and refuses nothing (a healthy record's first half-second, its demand ramping up from
    rest, was refused as ``x`` 2620 times its demand on the reference simulator, seed 1228); with ``u``
    too, on a loop that tracks its demand (``<x_ref, x> / <x, x>`` within a factor 2 of 1), the gain ``g = <u, e> / <e, e>`` of
    ``e = x_ref - x`` near ``KP / 1000``, with the drive explained better by ``KP e / 1000`` than by ``KP e``, names
    both. Near means within :data:`LOOP_SCALE_DECADES` of three decades."""
    import numpy as np

    from fpdd.errors import DataError

    found = _loop_signals(signals, ("x", "x_ref", "u") if "u" in signals else ("x", "x_ref"))
    if found is None:
        return
    x, r = found[0], found[1]
    u = found[2] if len(found) > 2 else None

    def thousand(ratio: float) -> int:
        """+1 for ~1000, -1 for ~1/1000, 0 otherwise."""
        if not (ratio > 0 and np.isfinite(ratio)):
            return 0
        d = np.log10(ratio)
        return 1 if abs(d - 3) <= LOOP_SCALE_DECADES else -1 if abs(d + 3) <= LOOP_SCALE_DECADES else 0

    def refuse(sig: str, why: str) -> None:
        raise DataError(f"{name}: {sig} {why}: it reads like a column in mm read as metres; give its unit: "
                        f"--map {sig}={sig}:mm or a header {sig}[mm] (a bare column is SI)")

    xx, rr = float(np.dot(x, x)), float(np.dot(r, r))
    b, lo_b, hi_b = _scale_interval(r, x)
    if thousand(lo_b) == 1 and thousand(hi_b) == 1:
        refuse("x", f"is {b:.3g} times larger than the demand x_ref it tracks")
    if thousand(lo_b) == -1 and thousand(hi_b) == -1:
        refuse("x_ref", f"is {1.0 / b:.3g} times larger than the position x that tracks it")
    try:
        kp = float(ps["KP"])
    except Exception:  # a model with no proportional gain
        return
    if u is None or not kp > 0:
        return
    if not (xx > 0 and rr > 0 and 0.5 <= float(np.dot(r, x)) / xx <= 2.0):
        return  # the gain is read only off a loop that tracks its demand (x and x_ref on one scale)
    e = r - x
    ee, ue = float(np.dot(e, e)), float(np.dot(u, e))
    if not (ee > 0 and ue > 0):
        return
    # the drive read as mm explains it better than read as SI (the residuals of u = KP e against u = KP e / 1000),
    # and the fitted gain is three decades below KP
    sse_si = float(np.sum((u - kp * e) ** 2))
    sse_mm = float(np.sum((u - kp * e / 1000.0) ** 2))
    if sse_mm < sse_si and thousand(kp * ee / ue) == 1:
        g = ue / ee
        raise DataError(f"{name}: x and x_ref drive the loop as if its gain were {g:.3g} V/m, about 1000 times less "
                        f"than KP = {kp:g} V/m: they read like columns in mm read as metres; give their units: "
                        "--map x=x:mm --map x_ref=x_ref:mm or headers x[mm], x_ref[mm] (a bare column is SI)")
