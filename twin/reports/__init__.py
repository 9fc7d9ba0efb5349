"""One self-contained HTML report per command (``--report DIR``), all in one style.

* :func:`fit_report` (``twin fit``): compare, resid, parameters with HAC and
  textbook standard errors, correlation matrix, loop timing;
* :func:`paper_report` (``twin paper``): the cases with our error beside the paper's;
* :func:`diagnose_report` (``twin diagnose``): nominal vs extended, gains with
  their intervals, corrected p-values, the verdict; :func:`write_diagnosis` writes it
  with its plots and JSON files (``twin diagnose --report DIR``);
* :func:`track_report` (``twin track``): parameter trends with band and 95 %
  interval, alarms, statuses.

Plots are PNG embedded as base64, CSS inline: the file needs no network and no
other file.  Parameters are in their display units (:mod:`twin.reports.units`).
"""

from __future__ import annotations


def fit_report(*args, **kw):
    from twin.reports.fit import fit_report as f

    return f(*args, **kw)


def paper_report(*args, **kw):
    from twin.paper.report import paper_report as f

    return f(*args, **kw)


def diagnose_report(*args, **kw):
    from twin.reports.diagnose import diagnose_report as f

    return f(*args, **kw)


def write_diagnosis(*args, **kw):
    from twin.reports.diagnose import write_diagnosis as f

    return f(*args, **kw)


def track_report(*args, **kw):
    from twin.reports.track import track_report as f

    return f(*args, **kw)


def track_summary(*args, **kw):
    from twin.reports.track import track_summary as f

    return f(*args, **kw)


__all__ = ["fit_report", "paper_report", "diagnose_report", "write_diagnosis", "track_report", "track_summary"]
