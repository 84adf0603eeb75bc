"""cloudct: 3D cloud tomography by differentiable Monte Carlo radiative transfer."""

__version__ = "0.1.0"
