"""The sun: a collimated source whose irradiance on a plane perpendicular to its rays is 1.

The sun is given by its zenith angle theta0 (0 = overhead) and the azimuth phi0 of the
direction TOWARDS it (from +x toward +y); photons travel along minus that unit vector.

Forward photons start on the sunlit faces of the box (``open`` boundaries: the top and the
side faces facing the sun; ``periodic``: the top only). The power entering through a face is
its area times |n . s| (its projection on the plane perpendicular to the rays), so a face is
chosen with probability proportional to that projected area, the point uniformly on it, and
every photon carries the total projected area as its weight: the estimator of Eq. (38) is
then absolute in the conventions' units (radiance in units of the solar irradiance).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

#: Faces a forward photon can enter through, in the order of ``SunArrays.face_cdf``.
FACE_TOP, FACE_XMIN, FACE_XMAX, FACE_YMIN, FACE_YMAX = range(5)


@dataclass(frozen=True)
class Sun:
    """Solar geometry in degrees: zenith angle and azimuth of the direction towards the sun."""

    zenith: float = 0.0
    azimuth: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.zenith) and math.isfinite(self.azimuth)):
            raise ValueError("sun zenith and azimuth must be finite")
        if not 0.0 <= self.zenith < 90.0:
            raise ValueError(
                f"sun zenith angle must be in [0, 90) degrees (sun above the horizon), "
                f"got {self.zenith}"
            )

    def travel_direction(self) -> np.ndarray:
        """Unit vector along which sunlight travels (minus the direction to the sun)."""
        th = math.radians(self.zenith)
        ph = math.radians(self.azimuth)
        return -np.array([math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), math.cos(th)])


class SunArrays(NamedTuple):
    """Kernel-side sun: travel direction, face-choice CDF and the weight of each photon."""

    direction: np.ndarray  # float64[3], direction of travel of sunlight
    face_cdf: np.ndarray  # float64[5], cumulative projected areas / total
    power: float  # total projected area of the sunlit faces, km^2 (irradiance 1)


def sun_arrays(sun: Sun, edges: tuple[np.ndarray, np.ndarray, np.ndarray], periodic: bool):
    """Sunlit-face projected areas of the box with the given cell edges."""
    s = sun.travel_direction()
    xe, ye, ze = edges
    lx, ly, lz = xe[-1] - xe[0], ye[-1] - ye[0], ze[-1] - ze[0]
    areas = np.zeros(5)
    areas[FACE_TOP] = lx * ly * -s[2]
    if not periodic:
        # a side face is lit when sunlight travels into it (n . s < 0)
        areas[FACE_XMIN] = ly * lz * max(s[0], 0.0)
        areas[FACE_XMAX] = ly * lz * max(-s[0], 0.0)
        areas[FACE_YMIN] = lx * lz * max(s[1], 0.0)
        areas[FACE_YMAX] = lx * lz * max(-s[1], 0.0)
    power = float(areas.sum())
    return SunArrays(direction=s, face_cdf=np.cumsum(areas) / power, power=power)


@njit(cache=True)
def sample_entry_point(grid, sun, u_face, u1, u2):
    """A point on a sunlit face, the face chosen with probability proportional to its
    projected area and the point uniform on it."""
    xe = grid.x_edges
    ye = grid.y_edges
    ze = grid.z_edges
    face = 0
    while face < 4 and u_face > sun.face_cdf[face]:
        face += 1
    if face == FACE_TOP:
        return xe[0] + u1 * (xe[-1] - xe[0]), ye[0] + u2 * (ye[-1] - ye[0]), ze[-1]
    if face == FACE_XMIN or face == FACE_XMAX:
        x = xe[0] if face == FACE_XMIN else xe[-1]
        return x, ye[0] + u1 * (ye[-1] - ye[0]), ze[0] + u2 * (ze[-1] - ze[0])
    y = ye[0] if face == FACE_YMIN else ye[-1]
    return xe[0] + u1 * (xe[-1] - xe[0]), y, ze[0] + u2 * (ze[-1] - ze[0])
