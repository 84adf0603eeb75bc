"""Gradient estimators: cost, precision and signal per second."""
