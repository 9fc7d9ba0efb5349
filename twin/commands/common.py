"""Small helpers shared by the command-line entry points (argument parsing, JSON output)."""

from __future__ import annotations

import sys


from fpdd import jsonio
from fpdd.errors import ParameterError


def kv(text: str | None) -> dict[str, float]:
    """``"a=1,wn=43Hz,CdAleak=3.3mm^2"`` -> SI floats; a bare number is SI, a unit is converted
    (:func:`twin.units.to_si`)."""
    from twin.units import to_si

    out: dict[str, float] = {}
    for part in (text or "").split(","):
        if not part.strip():
            continue
        if "=" not in part:
            raise ParameterError(f"expected NAME=VALUE, got {part!r}")
        k, v = part.split("=", 1)
        out[k.strip()] = to_si(k.strip(), v)
    return out


def names(text: str | None) -> tuple[str, ...]:
    return tuple(p.strip() for p in (text or "").split(",") if p.strip())


def progress(args):
    if getattr(args, "quiet", False):
        return None
    return lambda msg: print(msg, file=sys.stderr, flush=True)


#: The exit statuses of the commands that read records (their ``--help`` ends with it).
EXIT_HELP = ("exit status: 0 ok, 2 refused input or configuration (one line naming file and cause) or bad command "
             "line, 3 completed but a reader lost input on the way (a warning line on stderr says what; "
             "input_lost in --json)")


def loss_lines(command: str, reports) -> list[str]:
    """What the readers lost (one line per damaged input, :meth:`replay.base.ReadReport.loss_line`), each also
    said on stderr as ``twin COMMAND: warning: ...``; the command then exits with ``EXIT_LOSS`` (3)."""
    lines = [r.loss_line() for r in reports if r.lossy]
    for line in lines:
        print(f"twin {command}: warning: {line}", file=sys.stderr, flush=True)
    return lines


def dump(obj) -> None:
    """Print ``obj`` as strict JSON (NaN and infinities become null)."""
    print(jsonio.dumps(obj))


def load_params_file(model, path: str | None, overrides: dict[str, float] | None = None,
                     effects: tuple[str, ...] = (), with_timing: bool = False):
    """A parameter set from a JSON file written by ``twin fit --save`` or ``twin diagnose --save``
    (``{"model", "effects", "params"[, "timing"]}``), with ``effects`` added and ``overrides`` applied;
    with ``with_timing`` also the saved loop timing (or None)."""
    from twin.online.commission import read_saved
    from fpdd.errors import ConfigError

    doc: dict = {"effects": [], "params": {}}
    if path:
        doc = read_saved(path, "parameter file")
        if not isinstance(doc, dict):
            raise ConfigError(f"{path}: expected a JSON object written by twin fit --save or twin diagnose --save")
        if doc.get("model", model.name) != model.name:
            raise ConfigError(f"{path}: parameters of model {doc.get('model')!r}, expected {model.name!r}")
        if not isinstance(doc.get("params", {}), dict) or not isinstance(doc.get("effects", []), list):
            raise ConfigError(f"{path}: expected 'params' (an object) and 'effects' (a list)")
    ps = model.params(effects=tuple(doc.get("effects", [])) + tuple(effects))
    from twin.online.commission import check_unit

    known = {}
    for k, v in doc.get("params", {}).items():
        if k in ps.names:
            if isinstance(v, dict):  # {"value", "unit"[, "std"]} in SI (twin fit --save), or a bare number
                check_unit(path or "", f"params.{k}", v, ps.spec(k).unit)
                v = v.get("value")
            known[k] = v
    ps = ps.update({**known, **(overrides or {})})
    if not with_timing:
        return ps
    timing = None
    if isinstance(doc.get("timing"), dict):
        from twin.models.base import Timing

        t = doc["timing"]
        try:
            timing = Timing(t.get("controller", "digital"), t.get("rate_hz"), t.get("intersample"))
        except ParameterError as exc:
            raise ConfigError(f"{path}: timing: {exc}") from None
    return ps, timing


def add_timing_arguments(p) -> None:
    """``--controller`` and ``--intersample``: the loop's timing, a property of the rig."""
    p.add_argument("--controller", default=None, metavar="KIND",
                   help="the rig's controller: digital (at the log's rate, default), digital:RATE (a digital "
                        "controller at RATE Hz, faster than the log, e.g. digital:5000) or continuous (analog)")
    p.add_argument("--intersample", default=None, choices=("zoh", "foh", "cubic"),
                   help="logged inputs between samples: held (zoh), linear (foh) or smooth (cubic); default zoh "
                        "for a digital controller at the log's rate, else cubic")


def timing_of(args, default=None):
    """The :class:`~twin.models.base.Timing` the flags ask for (``default`` where neither is given)."""
    from twin.models.base import Timing

    controller = getattr(args, "controller", None)
    intersample = getattr(args, "intersample", None)
    if controller is None and intersample is None and default is not None:
        return default
    timing = Timing.parse(controller, intersample)
    from twin.service.config_parse import MAX_CONTROLLER_HZ

    if timing.rate_hz is not None and timing.rate_hz > MAX_CONTROLLER_HZ:
        from fpdd.errors import ParameterError

        raise ParameterError(f"--controller: a digital controller at {timing.rate_hz:g} Hz; at most "
                             f"{MAX_CONTROLLER_HZ:g} Hz (servo-hydraulic controllers run at 1-10 kHz)")
    return timing


def add_map_argument(p) -> None:
    """``--map NAME=COLUMN[:UNIT][*GAIN][+OFFSET]`` (repeatable): read a record whose columns (a CSV's or a text
    file's, a MATLAB file's variables, a CAN log's DBC signals) have other names, units or scales."""
    from replay.options import MAP_HELP

    p.add_argument("--map", action="append", metavar="NAME=COLUMN[:UNIT][*GAIN][+OFFSET]", help=MAP_HELP)
    if "--dbc" not in p._option_string_actions:  # a CAN log's DBC, its signals mapped with --map
        p.add_argument("--dbc", metavar="FILE", help="DBC for CAN logs (default: the MSP25 DBC shipped); your own "
                       "DBC's signals are mapped with --map, e.g. --map x=MyPosSignal:mm")
    from replay.options import add_rate_options

    add_rate_options(p)


def source_options(args, path: str) -> dict:
    """Reader options for ``path`` from ``--map`` (a column mapping), ``--dbc`` (a CAN log's DBC) and
    ``--rate``/``--dt``, checked."""
    from replay.options import rate_options

    try:
        rate = rate_options(args, path)
    except Exception as exc:  # argparse.ArgumentTypeError: a plain one-line message
        from fpdd.errors import DataError

        raise DataError(str(exc)) from None
    from replay import formats

    if getattr(args, "dbc", None):
        if not formats.is_can_log(path):
            from fpdd.errors import DataError

            raise DataError(f"{path}: --dbc decodes CAN logs ({', '.join(formats.CAN_LOG_SUFFIXES)}); this file is "
                            "not one")
        rate = {**rate, "dbc": args.dbc}
    items = getattr(args, "map", None)
    if not items:  # the map a commissioning file (--params) was fitted through, with its units
        from twin.online.commission import saved_map

        items = saved_map(getattr(args, "params", None), path)
    if not items:
        return rate
    if not formats.takes_map(path):
        from fpdd.errors import DataError

        raise DataError(f"{path}: --map maps the columns of CSV, text and MATLAB files and the signals of CAN logs; "
                        "this file is not a CSV, text, MATLAB file or CAN log (its signals are named by its format)")
    from replay.csvio import parse_map

    return {"mapping": parse_map(items), **rate}
