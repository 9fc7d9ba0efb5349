"""fpdd: the bottom layer that ``replay`` and ``twin`` share, importing neither.

:mod:`fpdd.errors` the exception tree, :mod:`fpdd.jsonio` strict JSON, :mod:`fpdd.argtypes` argparse types,
:mod:`fpdd.zenohconf` the one Zenoh configuration, :mod:`fpdd.units` the signals' units, display units and
nominal noise, and values with units on the way in.
"""
