"""Cameras: definition, netCDF form, and projection onto pixels.

A camera at ``position`` looks at ``lookat``; ``up`` fixes the image's vertical (it need
not be orthogonal to the view direction). Pixels are square. Image arrays are [row, col],
row 0 at the top (the camera's up side) and col 0 on the left as seen looking along the
view direction (CONVENTIONS.md). Two projections:

- ``pinhole`` (the default): perspective through the pinhole at ``position``; ``fov`` is
  the full field of view across the image's columns (the horizontal axis).
- ``orthographic``: parallel rays along the view direction through an image rectangle
  centred on ``position``, perpendicular to the view direction, ``width`` km across the
  columns; ``fov`` is ignored. A pixel's value is the average, over the pixel's area on
  that rectangle, of the radiance travelling along minus the view direction. A point
  source of intensity J [power/sr] in that direction adds J / a to its pixel, a the
  pixel's area [km^2] (docs/sensors.md).

Both serve every estimator (forward and backward renders, the score-function, DRT and
sample-matching gradients, path recycling) on both back ends, and space carving: the
kernels see a camera only through :func:`project` and :func:`pixel_ray`, carving through
their vectorised twins in :mod:`cloudct.retrieval.cloudy_pixels`.

On the image plane at unit distance in front of the pinhole, a direction d (from the pinhole
towards the scene) lands at u = d.right / d.forward, v = d.up / d.forward. A pixel's value is
the average radiance over its area a on that plane. A point source of intensity J [power/sr]
at distance r, seen at angle alpha from the optical axis, therefore adds J / (r^2 Omega) to
its pixel, with Omega = a cos^3(alpha) the pixel's solid angle in that direction (seed paper
Eqs. (37)-(39) with the box-filter detector response W_d = 1 / Omega).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import xarray as xr
from numba import njit

#: Camera projections, in the order of their kernel codes (:data:`PINHOLE`, ...).
PROJECTIONS = ("pinhole", "orthographic")
#: Kernel codes of ``CameraArrays.projection``. DOMAIN is not a camera: a one-pixel sensor
#: that sees every event once and divides by the domain's projected area (the radiance
#: probes of :mod:`cloudct.mc.sensors`).
PINHOLE, ORTHOGRAPHIC, DOMAIN = 0, 1, 2


@dataclass(frozen=True)
class Camera:
    """A camera (positions and ``width`` in km, field of view in degrees): a pinhole, or
    with ``projection="orthographic"`` parallel rays through a ``width``-km-wide image
    rectangle centred on ``position`` (``fov`` ignored)."""

    position: tuple[float, float, float]
    lookat: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    fov: float = 40.0
    nrows: int = 76
    ncols: int = 76
    projection: str = "pinhole"
    width: float | None = None

    def __post_init__(self) -> None:
        if self.projection not in PROJECTIONS:
            raise ValueError(
                f"camera projection must be one of {PROJECTIONS}, got {self.projection!r}"
            )
        orthographic = self.projection == "orthographic"
        if orthographic and not (self.width is not None and math.isfinite(self.width)
                                 and self.width > 0.0):
            raise ValueError(f"an orthographic camera needs a width > 0 (km), got {self.width}")
        if not orthographic and self.width is not None:
            raise ValueError("only an orthographic camera has a width (a pinhole has a fov)")
        forward = np.subtract(self.lookat, self.position)
        if not np.all(np.isfinite(np.r_[self.position, self.lookat, self.up, self.fov])):
            raise ValueError("camera position, lookat, up and fov must be finite")
        if np.linalg.norm(forward) == 0.0:
            raise ValueError("camera lookat must differ from its position")
        if np.linalg.norm(np.cross(forward, self.up)) <= 1e-9 * np.linalg.norm(forward):
            raise ValueError("camera up vector must not be parallel to the view direction")
        if not 0.0 < self.fov < 180.0:
            raise ValueError(f"camera fov must be in (0, 180) degrees, got {self.fov}")
        if self.nrows < 1 or self.ncols < 1:
            raise ValueError("camera nrows and ncols must be positive")

    def frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit vectors (forward, right, up) of the camera frame."""
        forward = np.subtract(self.lookat, self.position).astype(float)
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, self.up)
        right /= np.linalg.norm(right)
        up = np.cross(right, forward)
        return forward, right, up

    def half_size(self) -> tuple[float, float]:
        """Half width and half height of the image: on the unit-distance image plane
        (pinhole, tan(fov / 2) across the columns), or of the image rectangle in km
        (orthographic)."""
        if self.projection == "orthographic":
            half_width = 0.5 * float(self.width)
        else:
            half_width = float(np.tan(np.radians(self.fov) / 2.0))
        return half_width, half_width * self.nrows / self.ncols

    def rays(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Origins and unit directions, each of shape (n, 3), of the rays through the
        image points (u, v) (along ``right`` and ``up``, in the units of
        :meth:`half_size`)."""
        forward, right, up = self.frame()
        offset = np.reshape(u, (-1, 1)) * right + np.reshape(v, (-1, 1)) * up
        position = np.asarray(self.position, dtype=float)
        if self.projection == "orthographic":
            return position + offset, np.broadcast_to(forward, offset.shape).copy()
        rays = forward + offset
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        return np.broadcast_to(position, rays.shape).copy(), rays


class CameraArrays(NamedTuple):
    """Kernel-side cameras (all views share the image size)."""

    position: np.ndarray  # float64[nview, 3], km
    forward: np.ndarray  # float64[nview, 3]
    right: np.ndarray  # float64[nview, 3]
    up: np.ndarray  # float64[nview, 3]
    half_width: np.ndarray  # float64[nview]: tan(fov / 2) on the unit-distance image plane
    # (pinhole), half the image rectangle's width in km (orthographic)
    half_height: np.ndarray  # float64[nview]
    pixel_area: np.ndarray  # float64[nview]: pixel area on the unit-distance image plane
    # (pinhole), in km^2 (orthographic), the domain's projected area (DOMAIN)
    projection: np.ndarray  # int64[nview]: PINHOLE, ORTHOGRAPHIC or DOMAIN
    nrows: int
    ncols: int
    #: share of forward scattering events that aim their new direction at a camera
    #: (:mod:`cloudct.mc.detector_sampling`); 0: plain phase-function sampling
    aim_fraction: float = 0.0
    #: backward samples per pixel over forward photons of the combined estimator
    #: (:mod:`cloudct.mc.combined`); 0: each estimator alone, unweighted
    mis_ratio: float = 0.0


def camera_arrays(cameras: list[Camera], aim_fraction: float = 0.0) -> CameraArrays:
    """Gather cameras, pinhole or orthographic (both serve everything that takes
    cameras), into kernel arrays; all cameras must share the image size.
    ``aim_fraction`` in [0, 1) is the forward estimator's detector directional importance
    sampling (:mod:`cloudct.mc.detector_sampling`)."""
    if not cameras:
        raise ValueError("at least one camera is needed")
    shapes = {(c.nrows, c.ncols) for c in cameras}
    if len(shapes) != 1:
        raise ValueError(f"all cameras must have the same image size, got {sorted(shapes)}")
    nrows, ncols = shapes.pop()
    if not 0.0 <= aim_fraction < 1.0:
        raise ValueError(
            f"aim_fraction must be in [0, 1) (0 switches aiming off), got {aim_fraction}"
        )
    frames = [c.frame() for c in cameras]
    half_width = np.array([c.half_size()[0] for c in cameras])
    half_height = half_width * nrows / ncols
    return CameraArrays(
        position=np.array([c.position for c in cameras], dtype=np.float64),
        forward=np.array([f[0] for f in frames]),
        right=np.array([f[1] for f in frames]),
        up=np.array([f[2] for f in frames]),
        half_width=half_width,
        half_height=half_height,
        pixel_area=(2.0 * half_width / ncols) * (2.0 * half_height / nrows),
        projection=np.array([PROJECTIONS.index(c.projection) for c in cameras], np.int64),
        nrows=nrows,
        ncols=ncols,
        aim_fraction=float(aim_fraction),
    )


@njit(cache=True, inline="always")
def project(cams, view, px, py, pz):
    """Pixel of camera ``view`` seeing the point (px, py, pz).

    Returns ``(row, col, dx, dy, dz, inverse_r2_omega)``: the pixel (row = -1 when the point
    is behind the camera or outside the image), the unit vector from the point towards the
    pinhole (orthographic and DOMAIN: minus the view direction), and 1 / (r^2 Omega_pixel)
    for that direction (orthographic: 1 / pixel area; DOMAIN: pixel 0, 0 for every point
    and 1 / the domain's projected area).
    """
    fx = cams.forward[view, 0]
    fy = cams.forward[view, 1]
    fz = cams.forward[view, 2]
    kind = cams.projection[view]
    if kind == DOMAIN:
        return 0, 0, -fx, -fy, -fz, 1.0 / cams.pixel_area[view]
    dx = px - cams.position[view, 0]
    dy = py - cams.position[view, 1]
    dz = pz - cams.position[view, 2]
    depth = dx * fx + dy * fy + dz * fz
    if depth <= 0.0:
        return -1, -1, 0.0, 0.0, 0.0, 0.0
    u = dx * cams.right[view, 0] + dy * cams.right[view, 1] + dz * cams.right[view, 2]
    v = dx * cams.up[view, 0] + dy * cams.up[view, 1] + dz * cams.up[view, 2]
    if kind == PINHOLE:
        u /= depth
        v /= depth
    hw = cams.half_width[view]
    hh = cams.half_height[view]
    if not (-hw <= u < hw and -hh < v <= hh):
        return -1, -1, 0.0, 0.0, 0.0, 0.0
    col = min(int((u + hw) / (2.0 * hw) * cams.ncols), cams.ncols - 1)
    row = min(int((hh - v) / (2.0 * hh) * cams.nrows), cams.nrows - 1)
    if kind == ORTHOGRAPHIC:
        return row, col, -fx, -fy, -fz, 1.0 / cams.pixel_area[view]
    r = math.sqrt(dx * dx + dy * dy + dz * dz)
    # r^2 * Omega = r^2 * a * cos^3(alpha) = a * depth^3 / r
    inverse_r2_omega = r / (cams.pixel_area[view] * depth * depth * depth)
    return row, col, -dx / r, -dy / r, -dz / r, inverse_r2_omega


@njit(cache=True, _nrt=False)
def inverse_r2_omega(cams, view, ux, uy, uz, r):
    """1 / (r^2 Omega_pixel) of :func:`project` for the point at distance ``r`` from the
    pinhole along the unit vector (ux, uy, uz) (orthographic: 1 / pixel area, whatever
    ``r``): the density per unit volume, over sigma T, of the backward ray's first vertex."""
    if cams.projection[view] != PINHOLE:
        return 1.0 / cams.pixel_area[view]
    cos_alpha = ux * cams.forward[view, 0] + uy * cams.forward[view, 1] + uz * cams.forward[view, 2]
    return 1.0 / (cams.pixel_area[view] * r * r * cos_alpha * cos_alpha * cos_alpha)


@njit(cache=True, _nrt=False)
def pixel_ray(cams, view, row, col, xi_u, xi_v):
    """Origin and unit direction ``(ox, oy, oz, dx, dy, dz)`` of the ray through the
    image-plane point of a pixel: from the pinhole, or (orthographic) from the point on the
    image rectangle along the view direction.

    (xi_u, xi_v) in [0, 1)^2 place the point uniformly over the pixel's area, so that the
    average over them is the box-filtered pixel value.
    """
    hw = cams.half_width[view]
    hh = cams.half_height[view]
    u = -hw + (col + xi_u) * (2.0 * hw / cams.ncols)
    v = hh - (row + xi_v) * (2.0 * hh / cams.nrows)
    ox = cams.position[view, 0]
    oy = cams.position[view, 1]
    oz = cams.position[view, 2]
    if cams.projection[view] == ORTHOGRAPHIC:
        ox += u * cams.right[view, 0] + v * cams.up[view, 0]
        oy += u * cams.right[view, 1] + v * cams.up[view, 1]
        oz += u * cams.right[view, 2] + v * cams.up[view, 2]
        return ox, oy, oz, cams.forward[view, 0], cams.forward[view, 1], cams.forward[view, 2]
    dx = cams.forward[view, 0] + u * cams.right[view, 0] + v * cams.up[view, 0]
    dy = cams.forward[view, 1] + u * cams.right[view, 1] + v * cams.up[view, 1]
    dz = cams.forward[view, 2] + u * cams.right[view, 2] + v * cams.up[view, 2]
    norm = math.sqrt(dx * dx + dy * dy + dz * dz)
    return ox, oy, oz, dx / norm, dy / norm, dz / norm


def cameras_dataset(cameras: list[Camera]) -> xr.Dataset:
    """Cameras as a Dataset over ``view`` (netCDF-ready, CF attributes)."""
    xyz = ["x", "y", "z"]
    ds = xr.Dataset(
        {
            "position": (("view", "xyz"), np.array([c.position for c in cameras], float)),
            "lookat": (("view", "xyz"), np.array([c.lookat for c in cameras], float)),
            "up": (("view", "xyz"), np.array([c.up for c in cameras], float)),
            "fov": ("view", np.array([c.fov for c in cameras], float)),
            "nrows": ("view", np.array([c.nrows for c in cameras], np.int32)),
            "ncols": ("view", np.array([c.ncols for c in cameras], np.int32)),
            "projection": ("view", np.array([PROJECTIONS.index(c.projection)
                                             for c in cameras], np.int8)),
            "width": ("view", np.array([np.nan if c.width is None else c.width
                                        for c in cameras], float)),
        },
        coords={"view": np.arange(len(cameras)), "xyz": xyz},
    )
    ds["position"].attrs.update(
        units="km", long_name="pinhole position (orthographic: centre of the image rectangle)"
    )
    ds["lookat"].attrs.update(units="km", long_name="point the camera looks at")
    ds["up"].attrs.update(units="1", long_name="up vector of the image")
    ds["fov"].attrs.update(units="degree", long_name="full field of view across the columns")
    ds["nrows"].attrs.update(units="1", long_name="image rows")
    ds["ncols"].attrs.update(units="1", long_name="image columns")
    ds["projection"].attrs.update(
        units="1", long_name="camera projection", flag_values=np.arange(len(PROJECTIONS),
                                                                        dtype=np.int8),
        flag_meanings=" ".join(PROJECTIONS),
    )
    ds["width"].attrs.update(
        units="km", long_name="width of an orthographic camera's image across the columns",
        comment="NaN for a pinhole camera",
    )
    ds["view"].attrs.update(long_name="camera index")
    return ds


def cameras_from_dataset(ds: xr.Dataset) -> list[Camera]:
    """The cameras stored in a Dataset written by :func:`cameras_dataset` (files without
    ``projection`` hold pinholes)."""
    missing = [v for v in ("position", "lookat", "up", "fov", "nrows", "ncols") if v not in ds]
    if missing:
        raise ValueError(f"camera variables missing: {', '.join(missing)}")
    nview = ds.sizes["view"]
    codes = ds["projection"].values if "projection" in ds else np.zeros(nview, np.int8)
    if np.any((codes < 0) | (codes >= len(PROJECTIONS))):
        raise ValueError(f"camera projection codes must be 0 (pinhole) or 1 (orthographic), "
                         f"got {sorted(set(codes.tolist()))}")
    widths = ds["width"].values if "width" in ds else np.full(nview, np.nan)
    return [
        Camera(
            position=tuple(float(v) for v in ds["position"].values[i]),
            lookat=tuple(float(v) for v in ds["lookat"].values[i]),
            up=tuple(float(v) for v in ds["up"].values[i]),
            fov=float(ds["fov"].values[i]),
            nrows=int(ds["nrows"].values[i]),
            ncols=int(ds["ncols"].values[i]),
            projection=PROJECTIONS[int(codes[i])],
            width=None if PROJECTIONS[int(codes[i])] == "pinhole" else float(widths[i]),
        )
        for i in range(nview)
    ]


def travel_direction(zenith: float, azimuth: float) -> np.ndarray:
    """Unit vector of light propagating at ``zenith`` degrees from +z (up to 90: leaving
    upward; beyond 90: downward) and ``azimuth`` degrees from +x toward +y."""
    th, ph = math.radians(zenith), math.radians(azimuth)
    return np.array([math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), math.cos(th)])


def orthographic_camera(
    target: tuple[float, float, float],
    zenith: float,
    azimuth: float,
    *,
    width: float,
    nrows: int,
    ncols: int | None = None,
    distance: float = 10.0,
) -> Camera:
    """An orthographic camera whose pixels record the light that travels in direction
    (``zenith``, ``azimuth``) (degrees; :func:`travel_direction`: zenith < 90 light going up,
    seen from above; > 90 going down, seen from below), its image ``width`` km wide
    centred on the ray through ``target``, the rectangle ``distance`` km from it. The
    image's up is +z, or +y for a vertical view."""
    travel = travel_direction(zenith, azimuth)
    position = np.asarray(target, dtype=float) + distance * travel
    vertical = abs(travel[2]) > 1.0 - 1e-12
    return Camera(
        tuple(position), tuple(float(t) for t in target),
        (0.0, 1.0, 0.0) if vertical else (0.0, 0.0, 1.0), nrows=nrows,
        ncols=nrows if ncols is None else ncols, projection="orthographic", width=width,
    )


def ring_cameras(
    target: tuple[float, float, float],
    *,
    distance: float,
    zenith: float,
    azimuths: list[float] | np.ndarray,
    fov: float,
    npix: int,
    include_zenith: bool = True,
) -> list[Camera]:
    """Cameras aimed at ``target`` from ``distance`` km: one at the zenith and a ring.

    The ring cameras sit ``zenith`` degrees from the vertical at the given azimuths
    (degrees from +x toward +y); their images have +z up. The zenith camera's image has
    +y (north) up.
    """
    target_arr = np.asarray(target, dtype=float)
    cams = []
    if include_zenith:
        cams.append(
            Camera(
                position=tuple(target_arr + [0.0, 0.0, distance]),
                lookat=tuple(target_arr),
                up=(0.0, 1.0, 0.0),
                fov=fov,
                nrows=npix,
                ncols=npix,
            )
        )
    th = np.radians(zenith)
    for az in np.radians(np.asarray(azimuths, dtype=float)):
        offset = distance * np.array([np.sin(th) * np.cos(az), np.sin(th) * np.sin(az), np.cos(th)])
        up = (0.0, 0.0, 1.0) if zenith > 1e-6 else (0.0, 1.0, 0.0)
        position = tuple(target_arr + offset)
        cams.append(Camera(position, tuple(target_arr), up, fov=fov, nrows=npix, ncols=npix))
    return cams


#: The widest field of view [deg] that :func:`box_fitting_fov` fits: wider pinhole images
#: squeeze the box into a few central pixels.
MAX_FITTED_FOV = 150.0


def box_fitting_fov(
    box_min: np.ndarray, box_max: np.ndarray, distance: float, margin: float = 1.05
) -> float:
    """Full field of view (degrees) in which a camera at ``distance`` from the box centre
    sees the whole box from any direction (the box's circumscribed sphere, with a margin)."""
    radius = 0.5 * float(np.linalg.norm(np.subtract(box_max, box_min)))
    if radius >= distance:
        raise ValueError("cameras must be farther from the box centre than its half-diagonal")
    if margin * radius / distance > math.sin(math.radians(MAX_FITTED_FOV / 2.0)):
        needed = margin * radius / math.sin(math.radians(MAX_FITTED_FOV / 2.0))
        raise ValueError(
            f"the box (half-diagonal {radius:.3g} km) is too wide to be framed from "
            f"{distance:.3g} km: its field of view would exceed {MAX_FITTED_FOV:g} degrees; "
            f"place the cameras at least {needed:.3g} km from its centre, or give a field of "
            "view that frames a part of it"
        )
    return float(2.0 * np.degrees(np.arcsin(margin * radius / distance)))


def nine_camera_set(
    box_min: np.ndarray,
    box_max: np.ndarray,
    *,
    distance: float = 2.0,
    ring_zenith: float = 29.0,
    npix: int = 76,
    fov: float | None = None,
) -> list[Camera]:
    """The seed paper's nine cameras: zenith + eight on a ring, aimed at the box centre.

    Ring at ``ring_zenith`` degrees from the zenith, azimuths 0, 45, ..., 315; all at
    ``distance`` km from the box centre with ``npix`` x ``npix`` images. The field of view
    defaults to one that frames the whole box (:func:`box_fitting_fov`).
    """
    centre = 0.5 * (np.asarray(box_min, float) + np.asarray(box_max, float))
    if fov is None:
        fov = box_fitting_fov(box_min, box_max, distance)
    return ring_cameras(
        tuple(centre),
        distance=distance,
        zenith=ring_zenith,
        azimuths=np.arange(0.0, 360.0, 45.0),
        fov=fov,
        npix=npix,
    )
