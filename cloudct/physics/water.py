"""Refractive index of liquid water from 0.2 to 2.6 micron: the table of Hale & Querry (1973).

Source: G. M. Hale and M. R. Querry, "Optical constants of water in the 200-nm to 200-um
wavelength region", Appl. Opt. 12, 555-563 (1973), doi:10.1364/AO.12.000555: liquid water at
25 C. :data:`HALE_QUERRY_1973` holds the paper's rows from 0.200 to 2.6 micron as published
(three decimals of n, three significant digits of k), transcribed from the public-domain
copy of the refractiveindex.info database (``database/data/main/H2O/nk/Hale.yml``). The
table steps 0.025 micron up to 1 micron, then 0.2 micron; near infrared values between
the tabulated points (e.g. 1.65 and 2.13 micron) are therefore interpolations across
absorption bands (1.45 and 1.94 micron) that the table does not resolve.

Convention: m = n + i k, k >= 0 absorbing. Between tabulated points n is interpolated
linearly in wavelength and k log-linearly (ln k linear in wavelength): k spans seven
decades over the range and changes by up to a factor of 14 between neighbouring rows.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from cloudct.physics import wavelengths_within

SOURCE = "Hale and Querry (1973), Appl. Opt. 12, 555"

#: (wavelength [micron], n, k) of liquid water, Hale & Querry (1973), 0.2 to 2.6 micron.
HALE_QUERRY_1973 = np.array(
    [
        (0.200, 1.396, 1.10e-7),
        (0.225, 1.373, 4.90e-8),
        (0.250, 1.362, 3.35e-8),
        (0.275, 1.354, 2.35e-8),
        (0.300, 1.349, 1.60e-8),
        (0.325, 1.346, 1.08e-8),
        (0.350, 1.343, 6.50e-9),
        (0.375, 1.341, 3.50e-9),
        (0.400, 1.339, 1.86e-9),
        (0.425, 1.338, 1.30e-9),
        (0.450, 1.337, 1.02e-9),
        (0.475, 1.336, 9.35e-10),
        (0.500, 1.335, 1.00e-9),
        (0.525, 1.334, 1.32e-9),
        (0.550, 1.333, 1.96e-9),
        (0.575, 1.333, 3.60e-9),
        (0.600, 1.332, 1.09e-8),
        (0.625, 1.332, 1.39e-8),
        (0.650, 1.331, 1.64e-8),
        (0.675, 1.331, 2.23e-8),
        (0.700, 1.331, 3.35e-8),
        (0.725, 1.330, 9.15e-8),
        (0.750, 1.330, 1.56e-7),
        (0.775, 1.330, 1.48e-7),
        (0.800, 1.329, 1.25e-7),
        (0.825, 1.329, 1.82e-7),
        (0.850, 1.329, 2.93e-7),
        (0.875, 1.328, 3.91e-7),
        (0.900, 1.328, 4.86e-7),
        (0.925, 1.328, 1.06e-6),
        (0.950, 1.327, 2.93e-6),
        (0.975, 1.327, 3.48e-6),
        (1.000, 1.327, 2.89e-6),
        (1.200, 1.324, 9.89e-6),
        (1.400, 1.321, 1.38e-4),
        (1.600, 1.317, 8.55e-5),
        (1.800, 1.312, 1.15e-4),
        (2.000, 1.306, 1.10e-3),
        (2.200, 1.296, 2.89e-4),
        (2.400, 1.279, 9.56e-4),
        (2.600, 1.242, 3.17e-3),
    ]
)

_WAVELENGTH, _N, _K = HALE_QUERRY_1973.T
#: The wavelengths [micron] at which :func:`water_refractive_index` is defined.
WAVELENGTH_RANGE = (float(_WAVELENGTH[0]), float(_WAVELENGTH[-1]))


def water_refractive_index(wavelength: ArrayLike) -> complex | np.ndarray:
    """Refractive index m = n + i k of liquid water at ``wavelength`` [micron].

    Interpolated in the table of Hale & Querry (1973) (module documentation): n linearly,
    ln k linearly in wavelength; exact at the tabulated wavelengths.

    Args:
        wavelength: [micron], a number or an array, within :data:`WAVELENGTH_RANGE`.

    Returns:
        A complex number for a scalar ``wavelength``, else a complex array of its shape.

    Raises:
        ValueError: a wavelength outside :data:`WAVELENGTH_RANGE` (or not finite).
    """
    lam = wavelengths_within(
        wavelength, WAVELENGTH_RANGE, "refractive index of water at {bad} micron: the Hale & "
        "Querry (1973) table is used from {lo} to {hi} micron; pass refractive_index")
    n = np.interp(lam, _WAVELENGTH, _N)
    k = np.exp(np.interp(lam, _WAVELENGTH, np.log(_K)))
    m = n + 1j * k
    return complex(m) if m.ndim == 0 else m
