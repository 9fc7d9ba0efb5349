"""The online twin: the compiled augmented-state UKF, the tracker around it, the drift detector, its events, commissioning."""
