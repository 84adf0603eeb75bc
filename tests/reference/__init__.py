"""Independent reference solvers used to validate the cloudct Monte Carlo engine.

Nothing in this package imports :mod:`cloudct`; the solvers here are written from the
radiative-transfer equations alone so that agreement with the Monte Carlo engine is a
meaningful test.
"""
