"""Rig configuration (``rigs.toml``) for ``twin serve``: which rigs, where their data come from,
which parameters to track, their healthy baselines, and how to reach Zenoh.

Example (every key but ``rig.name`` and ``rig.source`` has a default)::

    [zenoh]                             # optional; with ZENOH_CONFIG=FILE set, only the keys
    mode = "peer"                       #   given here override that file
    listen = ["tcp/127.0.0.1:7447"]     # "client" mode goes through a site router (connect)
    connect = []

    [service]
    journal_dir = "/var/lib/fpdd/journal"  # one SQLite journal per rig: alarms and checkpoints
    out_dir = "/var/lib/fpdd/records"   # MCAP of estimates and alarms (optional)
    estimate_every = 50                 # publish an estimate every N samples
    workers = "auto"                    # worker processes: "auto", 0 = threads in this process, N
    checkpoint_s = 1.0                  # checkpoint each rig's state this often (wall clock)
    block_s = 0.1                       # samples are filtered in blocks of this much time (latency)
    lag_warn_s = 1.0                    # status 'degraded' when a rig is this far behind real time
    stale_s = 1.0                       # a live input quiet this long is 'stale_input'

    [failover]                          # optional: these rigs are shared with other services, one runs
    priority = 100                      #   each, the others stand by (keys: twin/service/ownership.py)

    [[rig]]
    name = "hall1-a"
    model = "..."                       # a registered model the online twin runs (default the product's rig)
    source = "can://socketcan/can0"     # or zenoh://KEYEXPR, or a log file (replayed)
    dbc = ""                            # default: the DBC shipped with replay (relative to this file)
    map = ["x=pos_mm:mm", "t=time:ms"]  # a log's columns (CSV, text, MATLAB) or CAN signals (logs, can://)
                                        #   under other names, units, gains (as --map; or a table:
                                        #   map = { x = "pos_mm:mm", t = "time:ms", u = "vir*35.15N/V" })
    speed = 1.0                         # replay speed for log sources (0 = as fast as possible)
    track = ["Ffric", "CdAleak", "Cd", "zeta", "wn"]
    commission = "commissioning.json"   # a `twin fit --save` file (relative to this file): bands
                                        # centred on the fit, its noise levels and its timing
    # commission_s = 120                # or: commission the rig on its first 120 s in service
                                        # (status 'commissioning', no alarms until the fit is done;
                                        # saved as <journal_dir>/<rig>.commission.json and reused on
                                        # restart; a failed fit falls back to the configured bands)
    controller = "digital"              # the loop's timing: digital, digital:5000, continuous
    intersample = "zoh"                 # logged inputs between samples: zoh, foh, cubic
    forecast_horizon_s = 3600           # early warning when a parameter leaves its band within this
    noise = { x = "2um", pA = "20kPa", pB = "20kPa" }   # sensor noise (learnt online on top)
    [rig.params]                        # known parameters that differ from the model's nominal ones
    KP = 400.0                          # a bare number is SI; or with a unit: A = "2000mm^2"
    [rig.baseline.Ffric]                # healthy band (default: nominal value, the parameter's tracking band)
    value = 50.0                        # SI, or with a unit ("50N"; CdAleak = "0.0033mm^2"); a value outside
    rel_band = 0.3                      #   the parameter's bounds is refused; or lo = ..., hi = ...

Every error is one line naming the file, the key and what was expected; an
unknown key is an error that suggests the closest known one
(``rig 'a': unknown key 'trak' (did you mean 'track'?)``); numbers must be
finite (TOML's ``nan`` and ``inf`` are refused).

Reading is two steps, and this module is what the service calls (:func:`load_config`, :func:`parse_config`):
:mod:`twin.service.config_parse` reads the text into plain dataclasses and checks all that the text alone
decides; :mod:`twin.service.config_resolve` loads the files it points to and builds each rig's parameters and
bands from its model (:class:`RigConfig`, :class:`ServiceConfig`).
"""

from __future__ import annotations

import dataclasses
import math

from fpdd.errors import ConfigError
from twin.service.config_parse import MIN_COMMISSION_S, parse_doc, parse_file
from twin.service.config_resolve import RigConfig, ServiceConfig, resolve_config

__all__ = ["RigConfig", "ServiceConfig", "load_config", "parse_config", "with_commission_s"]


def load_config(path: str) -> ServiceConfig:
    """Read and validate a rig configuration; errors name the file and the key."""
    return resolve_config(parse_file(path))


def parse_config(doc: dict, path: str = "<config>") -> ServiceConfig:
    """Validate a TOML document of a rig configuration (``path`` names it in messages and anchors its relative
    paths)."""
    return resolve_config(parse_doc(doc, path))


def with_commission_s(cfg: ServiceConfig, seconds: float | None) -> ServiceConfig:
    """``cfg`` with ``commission_s = seconds`` for every rig that has neither ``commission`` nor ``commission_s``
    (``twin serve --commission-s``)."""
    if seconds is None:
        return cfg
    if not (math.isfinite(seconds) and seconds >= MIN_COMMISSION_S):
        raise ConfigError(f"--commission-s: must be >= {MIN_COMMISSION_S:g} seconds, got {seconds:g}")
    rigs = tuple(r if (r.commission or r.commission_s) else dataclasses.replace(r, commission_s=float(seconds))
                 for r in cfg.rigs)
    return dataclasses.replace(cfg, rigs=rigs)
