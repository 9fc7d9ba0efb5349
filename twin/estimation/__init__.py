"""Batch estimation on recorded data: the output-error fit, residual statistics, noise models, the diagnosis and the paper's cases."""
