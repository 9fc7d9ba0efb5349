"""One light module per ``twin`` subcommand: ``add_arguments(parser)`` and ``run(args)``, heavy imports inside ``run``."""
