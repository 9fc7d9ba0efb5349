"""fpdd-twin: first-principle data-driven digital twin of servo-hydraulic test rigs."""

__version__ = "0.1.0"
