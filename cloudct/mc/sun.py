"""The sun: a collimated source whose irradiance on a plane perpendicular to its rays is 1.

The sun is given by its zenith angle theta0 (0 = overhead) and the azimuth phi0 of the
direction TOWARDS it (from +x toward +y); photons travel along minus that unit vector.

Forward photons start on the sunlit faces of the box (``open`` boundaries: the top and the
side faces facing the sun; ``periodic``: the top only). The power entering through a face is
its area times |n . s| (its projection on the plane perpendicular to the rays), so a face is
chosen with probability proportional to that projected area, the point uniformly on it, and
every photon carries the total projected area P as its weight: the estimator of Eq. (38) is
then absolute in the conventions' units (radiance in units of the solar irradiance).

Entry where the clouds are (``cloud_share`` m > 0): the sunlit faces are split into their
grid cells c (the top face's nx x ny, a lit side face's ny x nz or nx x nz), with
projected-area shares a_c (sum 1) and cloud weights g_c = 1 - exp(-tau_c), tau_c the optical
depth along the sun's ray from the cell's centre until it leaves the box. A photon enters
through cell c with probability

    p_c = (1 - m) a_c + m a_c g_c / sum_k a_k g_k,

at a point uniform in the cell, with the weight P a_c / p_c <= P / (1 - m). The expected
weight entering through any area is that of the uniform source, so the images stay
unbiased; the proposal does not depend on the photon's path, so the path score function
(the gradients) gains no term. m = 0, and a medium with no extinction on the sun's rays,
keep the uniform source (an empty cell table): bitwise the images of the uniform source.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from cloudct.mc.traversal import locate_point, optical_depth_to_exit
from cloudct.physics.mixing import OpticalGrid

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
    """Kernel-side sun: travel direction, face-choice CDF, the weight of each photon, for
    entry where the clouds are the entry cells' table (empty: uniform entry), and the share
    of backward paths' directions aimed at the sun."""

    direction: np.ndarray  # float64[3], direction of travel of sunlight
    face_cdf: np.ndarray  # float64[5], cumulative projected areas / total
    power: float  # total projected area of the sunlit faces, km^2 (irradiance 1)
    cloud_share: float  # m of the entry cells' mixture (0: uniform entry)
    cell_cdf: np.ndarray  # float64[ncells], cumulative p_c over the cells (empty: uniform)
    cell_weight: np.ndarray  # float64[ncells], a photon's weight P a_c / p_c per cell
    cell_start: np.ndarray  # int64[6], first cell of each face (FACE_TOP ...), then ncells
    #: share of backward scattering directions drawn about the direction to the sun
    #: (:mod:`cloudct.mc.detector_sampling`); 0: plain phase-function sampling
    aim_fraction: float = 0.0


def check_cloud_share(cloud_share: float) -> float:
    """``cloud_share`` (``entry_cloud_share`` of the API) as a float in [0, 1), or a
    ValueError."""
    share = float(cloud_share)
    if not (math.isfinite(share) and 0.0 <= share < 1.0):
        raise ValueError(
            f"entry_cloud_share must be a finite number in [0, 1) (the share of photons "
            f"entering where the clouds are; 0: uniform entry), got {cloud_share}"
        )
    return share


def sun_arrays(
    sun: Sun, edges: tuple[np.ndarray, np.ndarray, np.ndarray], periodic: bool,
    grid: OpticalGrid | None = None, cloud_share: float = 0.0,
) -> SunArrays:
    """The kernel-side sun of a box: its sunlit faces' projected areas and, for entry where
    the clouds are, the entry cells' table (see the module documentation).

    Parameters
    ----------
    sun
        The solar geometry.
    edges
        The box's cell edges (x, y, z) [km].
    periodic
        Periodic boundaries (light enters through the top only, rays wrap).
    grid
        The medium's :class:`~cloudct.physics.mixing.OpticalGrid` on those edges: needed
        when ``cloud_share`` > 0, for the optical depths of the sun's rays.
    cloud_share
        The share m in [0, 1) of the cloud-weighted density in the entry cells' mixture;
        0: uniform entry (an empty table).

    Returns
    -------
    :class:`SunArrays`; uniform entry (``cloud_share`` 0) also where no ray of the sun
    from a cell centre meets extinction.
    """
    cloud_share = check_cloud_share(cloud_share)
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
    uniform = SunArrays(
        direction=s, face_cdf=np.cumsum(areas) / power, power=power, cloud_share=0.0,
        cell_cdf=np.zeros(0), cell_weight=np.zeros(0), cell_start=np.zeros(6, np.int64),
    )
    if cloud_share == 0.0:
        return uniform
    if grid is None:
        raise ValueError("entry where the clouds are (cloud_share > 0) needs the medium's grid")
    share, centres, start = entry_cells(edges, areas)
    depth = entry_optical_depths(grid, centres, s, periodic)
    clouds = share * -np.expm1(-depth)  # a_c g_c
    if not clouds.sum() > 0.0:
        return uniform
    p = (1.0 - cloud_share) * share + cloud_share * clouds / clouds.sum()
    cdf = np.cumsum(p)
    cdf /= cdf[-1]
    return uniform._replace(cloud_share=cloud_share, cell_cdf=cdf,
                            cell_weight=power * share / p, cell_start=start)


def entry_cells(
    edges: tuple[np.ndarray, np.ndarray, np.ndarray], areas: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The grid cells of the sunlit faces (those with ``areas`` > 0), face by face in the
    order FACE_TOP ... FACE_YMAX: their shares a_c of the projected area (sum 1), their
    centres (float64[3, ncells]) and the first cell of each face (int64[6], then ncells).
    Within a face, cell (i, j) of its two axes (x, y for the top; y, z or x, z for the
    sides) is cell i * n_j + j."""
    xe, ye, ze = edges
    widths = [np.diff(e) for e in edges]
    mids = [0.5 * (e[:-1] + e[1:]) for e in edges]
    # per face: the two axes spanning it, the fixed axis and its coordinate
    faces = ((FACE_TOP, 0, 1, 2, ze[-1]), (FACE_XMIN, 1, 2, 0, xe[0]),
             (FACE_XMAX, 1, 2, 0, xe[-1]), (FACE_YMIN, 0, 2, 1, ye[0]),
             (FACE_YMAX, 0, 2, 1, ye[-1]))
    share, centres, start = [], [], np.zeros(6, np.int64)
    for face, a, b, fixed, level in faces:
        count = 0
        if areas[face] > 0.0:
            cell_area = np.outer(widths[a], widths[b]).ravel()
            share.append(cell_area * (areas[face] / cell_area.sum()))
            centre = np.empty((3, cell_area.size))
            centre[a] = np.repeat(mids[a], mids[b].size)
            centre[b] = np.tile(mids[b], mids[a].size)
            centre[fixed] = level
            centres.append(centre)
            count = cell_area.size
        start[face + 1] = start[face] + count
    share = np.concatenate(share)
    return share / share.sum(), np.concatenate(centres, axis=1), start


@njit(cache=True)
def entry_optical_depths(grid, centres, s, periodic):
    """Optical depth along the sun's rays (direction ``s``) from each entry cell's centre
    (float64[3, ncells] on the box's faces) until the ray leaves the box."""
    depth = np.empty(centres.shape[1])
    for c in range(depth.size):
        px, py, pz = centres[0, c], centres[1, c], centres[2, c]
        ix, iy, iz = locate_point(grid, px, py, pz, s[0], s[1], s[2])
        depth[c] = optical_depth_to_exit(grid, px, py, pz, s[0], s[1], s[2], ix, iy, iz,
                                         periodic)
    return depth


@njit(cache=True)
def sample_entry_point(grid, sun, u_face, u1, u2):
    """A point on a sunlit face and the photon's weight.

    Uniform entry (an empty cell table): the face chosen with probability proportional to
    its projected area, the point uniform on it, the weight the total projected area.
    Otherwise the entry cell is the one whose interval of ``sun.cell_cdf`` holds
    ``u_face`` (binary search), the point uniform in it, the weight ``sun.cell_weight``."""
    if sun.cell_cdf.size > 0:
        return sample_entry_cell(grid, sun, u_face, u1, u2)
    xe = grid.x_edges
    ye = grid.y_edges
    ze = grid.z_edges
    face = 0
    while face < 4 and u_face > sun.face_cdf[face]:
        face += 1
    if face == FACE_TOP:
        return (xe[0] + u1 * (xe[-1] - xe[0]), ye[0] + u2 * (ye[-1] - ye[0]), ze[-1],
                sun.power)
    if face == FACE_XMIN or face == FACE_XMAX:
        x = xe[0] if face == FACE_XMIN else xe[-1]
        return x, ye[0] + u1 * (ye[-1] - ye[0]), ze[0] + u2 * (ze[-1] - ze[0]), sun.power
    y = ye[0] if face == FACE_YMIN else ye[-1]
    return xe[0] + u1 * (xe[-1] - xe[0]), y, ze[0] + u2 * (ze[-1] - ze[0]), sun.power


@njit(cache=True)
def sample_entry_cell(grid, sun, u_face, u1, u2):
    """The entry point and weight of :func:`sample_entry_point` from the cell table: cell c
    with probability p_c (the first c with ``u_face <= cell_cdf[c]``), the point uniform
    in it (``u1`` along its first axis, ``u2`` along its second), weight P a_c / p_c."""
    lo = 0
    hi = sun.cell_cdf.size - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if u_face > sun.cell_cdf[mid]:
            lo = mid + 1
        else:
            hi = mid
    face = 0
    while face < 4 and lo >= sun.cell_start[face + 1]:
        face += 1
    local = lo - sun.cell_start[face]
    xe = grid.x_edges
    ye = grid.y_edges
    ze = grid.z_edges
    weight = sun.cell_weight[lo]
    if face == FACE_TOP:
        i, j = local // (ye.size - 1), local % (ye.size - 1)
        return (xe[i] + u1 * (xe[i + 1] - xe[i]), ye[j] + u2 * (ye[j + 1] - ye[j]), ze[-1],
                weight)
    k = local % (ze.size - 1)
    z = ze[k] + u2 * (ze[k + 1] - ze[k])
    if face == FACE_XMIN or face == FACE_XMAX:
        j = local // (ze.size - 1)
        x = xe[0] if face == FACE_XMIN else xe[-1]
        return x, ye[j] + u1 * (ye[j + 1] - ye[j]), z, weight
    i = local // (ze.size - 1)
    y = ye[0] if face == FACE_YMIN else ye[-1]
    return xe[i] + u1 * (xe[i + 1] - xe[i]), y, z, weight
