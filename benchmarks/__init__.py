"""Benchmarks, each printing its figures beside a baseline measured in the same run (``python -m benchmarks``)."""


def add_guard_option(ap) -> None:
    """``--guard KEY=VALUE`` (repeatable) on a measurement's argument parser: see :func:`apply_guard`."""
    ap.add_argument("--guard", action="append", metavar="KEY=VALUE", default=[],
                    help="a tracker guard setting for this run (twin.online.tracker.DEFAULT_GUARD; repeatable), "
                    "e.g. central_mean=0 noise_share=0: the weighted mean and the plain noise learning")


def apply_guard(pairs) -> str | None:
    """Set tracker guard settings (``KEY=NUMBER``) for every tracker this process makes from now on; returns a
    one-line error naming the bad pair, or None."""
    import math

    from twin.online.tracker import DEFAULT_GUARD

    for kv in pairs:
        key, _, val = kv.partition("=")
        try:
            number = float(val)
        except ValueError:
            number = math.nan
        if key not in DEFAULT_GUARD or not math.isfinite(number):
            return f"--guard: {kv!r} is not KEY=NUMBER with KEY one of {', '.join(DEFAULT_GUARD)}"
        DEFAULT_GUARD[key] = number
    return None
