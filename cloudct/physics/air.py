"""Air (Rayleigh scattering by molecules) from one wavelength to another.

The spectral dependence is that of the Rayleigh optical depth of Bodhaine, Wood, Dutton &
Slusser (1999), "On Rayleigh optical depth calculations", J. Atmos. Ocean. Tech. 16,
1854-1861, Eq. (30), their fit for sea level (1013.25 mb), 45 degrees latitude and 360 ppm
CO2, with the wavelength in micron:

    tau_R(lambda) = 0.0021520 (1.0455996 - 341.29061 lambda^-2 - 0.90230850 lambda^2)
                              / (1 + 0.0027059889 lambda^-2 - 85.968563 lambda^2).

The optical depth is the scattering cross section per molecule times the column of
molecules, so at any pressure (altitude) the extinction coefficient scales with wavelength
as tau_R does: beta(lambda) = beta(lambda_0) tau_R(lambda) / tau_R(lambda_0).

Range: 0.2 to 2.6 micron. The fit's denominator vanishes at 0.108 micron. Its
tau_R lambda^4 falls from 0.5 to 1.2 micron, as the dispersion of air makes it, then rises,
by 3 % from 1 to 2.13 micron and by 9 % to 2.6 micron, where the physical one keeps falling
slowly: in the near infrared the fit extrapolates to a few percent, on an air extinction
that is 2.7 % (1.65 micron) and 1.0 % (2.13 micron) of its value at 0.672 micron.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from cloudct.physics import wavelengths_within

#: The wavelengths [micron] at which :func:`rayleigh_optical_depth` is used.
WAVELENGTH_RANGE = (0.2, 2.6)


def rayleigh_optical_depth(wavelength: ArrayLike) -> np.ndarray | float:
    """Rayleigh optical depth of the atmosphere at sea level, Bodhaine et al. (1999) Eq. (30).

    Args:
        wavelength: [micron], within :data:`WAVELENGTH_RANGE`.

    Returns:
        tau_R, a float for a scalar ``wavelength``, else an array of its shape.

    Raises:
        ValueError: a wavelength outside :data:`WAVELENGTH_RANGE` (or not finite).
    """
    lam = wavelengths_within(wavelength, WAVELENGTH_RANGE, "Rayleigh scaling at {bad} micron: "
                             "Bodhaine et al. (1999) Eq. (30) is used from {lo} to {hi} micron")
    inv2 = lam**-2
    tau = (0.0021520 * (1.0455996 - 341.29061 * inv2 - 0.90230850 * lam**2)
           / (1.0 + 0.0027059889 * inv2 - 85.968563 * lam**2))
    return float(tau) if tau.ndim == 0 else tau


def air_extinction_at(extinction: ArrayLike, wavelength: float, given_at: float):
    """Air extinction at ``wavelength`` from its value ``extinction`` at ``given_at``.

    Args:
        extinction: air extinction [km-1] at ``given_at`` (a number or an array).
        wavelength, given_at: [micron], within :data:`WAVELENGTH_RANGE`.

    Returns:
        ``extinction * tau_R(wavelength) / tau_R(given_at)`` (Bodhaine et al. 1999,
        Eq. 30), exactly ``extinction`` when the two wavelengths are equal.
    """
    if wavelength == given_at:
        rayleigh_optical_depth(wavelength)  # the range check
        return extinction
    return extinction * (rayleigh_optical_depth(wavelength) / rayleigh_optical_depth(given_at))
