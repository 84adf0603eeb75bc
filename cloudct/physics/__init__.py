"""Optics of air and droplets: phase functions, particle mixing, Mie tables."""
