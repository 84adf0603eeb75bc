"""A scene: cameras, sun, boundary conditions and ground, with checks and netCDF form.

The checks reject what would otherwise give silently wrong images: cameras inside the
medium, cameras below a ground, cameras whose view misses the medium, and (periodic
boundaries) cameras that see the slab out to the horizon, where infinitely many periodic
images would be visible.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import xarray as xr

from cloudct.mc.cameras import (
    Camera,
    box_fitting_fov,
    cameras_dataset,
    cameras_from_dataset,
    ring_cameras,
)
from cloudct.mc.sun import Sun
from cloudct.medium import cell_edges
from cloudct.netcdf import InputFileError, load_netcdf

BOUNDARIES = ("open", "periodic")


@dataclass(frozen=True)
class Scene:
    """What a render needs besides the medium.

    ``ground_albedo`` is the albedo of a Lambertian ground at the bottom of the box, or None
    for no ground (light leaving through the bottom is lost; cameras may look from below).
    A black ground (0) and no ground give the same images from above. With ``open``
    boundaries the ground is the box's bottom face; with ``periodic`` boundaries it is
    horizontally infinite.
    """

    cameras: list[Camera]
    sun: Sun = field(default_factory=Sun)
    boundary: str = "open"
    ground_albedo: float | None = None

    def __post_init__(self) -> None:
        if self.boundary not in BOUNDARIES:
            raise ValueError(f"boundary must be one of {BOUNDARIES}, got {self.boundary!r}")
        if self.ground_albedo is not None and not 0.0 <= self.ground_albedo <= 1.0:
            raise ValueError(f"ground_albedo must be in [0, 1], got {self.ground_albedo}")
        if not self.cameras:
            raise ValueError("a scene needs at least one camera")

    @property
    def periodic(self) -> bool:
        """True for horizontally periodic boundaries."""
        return self.boundary == "periodic"

    def to_dataset(self) -> xr.Dataset:
        """The scene as a netCDF-ready Dataset (cameras over ``view``, the rest as attrs)."""
        ds = cameras_dataset(self.cameras)
        ds.attrs.update(
            title="cloudct scene",
            Conventions="CF-1.8",
            sun_zenith=self.sun.zenith,
            sun_azimuth=self.sun.azimuth,
            sun_azimuth_convention="direction towards the sun, degrees from +x toward +y",
            boundary=self.boundary,
            ground_albedo=-1.0 if self.ground_albedo is None else self.ground_albedo,
            ground_albedo_note="-1 means no ground",
        )
        return ds

    @classmethod
    def from_dataset(cls, ds: xr.Dataset) -> Scene:
        """The scene stored by :meth:`to_dataset`."""
        missing = [a for a in ("sun_zenith", "sun_azimuth", "boundary") if a not in ds.attrs]
        if missing:
            raise ValueError(f"scene attributes missing: {', '.join(missing)}")
        ground = float(ds.attrs.get("ground_albedo", -1.0))
        return cls(
            cameras=cameras_from_dataset(ds),
            sun=Sun(float(ds.attrs["sun_zenith"]), float(ds.attrs["sun_azimuth"])),
            boundary=str(ds.attrs["boundary"]),
            ground_albedo=None if ground < 0.0 else ground,
        )


def single_cloud_scene(box_min: np.ndarray, box_max: np.ndarray) -> Scene:
    """The seed paper's single-cloud scene geometry: nine 76x76 cameras at 2 km from the
    box centre (zenith + ring at 29 degrees), sun at the zenith, open boundaries
    (:func:`build_scene`'s ``single-cloud`` preset)."""
    return build_scene(box_min, box_max, preset="single-cloud")


def single_cloud_scene_of(medium: xr.Dataset) -> Scene:
    """:func:`single_cloud_scene` around the box of ``medium``'s grid: the scene of
    ``render`` and ``synth`` when none is given."""
    edges = cell_edges(medium)
    return single_cloud_scene(np.array([e[0] for e in edges]), np.array([e[-1] for e in edges]))


#: Named camera geometries: ring zenith angle [deg], distance from the box centre [km]
#: (None: fitted to the box, see :func:`build_scene`) and image size [pixels]. The first
#: two are the seed paper's Table 1 (single cloud; cloud field: 79 x 84 x 27 voxels,
#: 1.58 x 1.68 x 1.08 km).
PRESETS = {
    "single-cloud": {"ring_zenith": 29.0, "distance": 2.0, "npix": 76},
    "cloud-field": {"ring_zenith": 33.0, "distance": 2.16, "npix": 86},
    "nadir": {"ring_zenith": 10.0, "distance": None, "npix": 128},
}


def build_scene(
    box_min: np.ndarray,
    box_max: np.ndarray,
    *,
    preset: str = "single-cloud",
    ring_zenith: float | None = None,
    distance: float | None = None,
    npix: int | None = None,
    fov: float | None = None,
    azimuths: Sequence[float] | None = None,
    rings: Sequence[tuple[float, Sequence[float] | None]] | None = None,
    region: tuple[Sequence[float], Sequence[float]] | None = None,
    altitude: float | None = None,
    sun_zenith: float = 0.0,
    sun_azimuth: float = 0.0,
    boundary: str = "open",
    ground_albedo: float | None = None,
) -> Scene:
    """A zenith camera and a ring (azimuths 0, 45, ..., 315 unless ``azimuths`` [deg, from
    +x toward +y] are given) aimed at the box centre, from a preset (:data:`PRESETS`) with
    any of its numbers overridden.

    ``rings`` replaces the one ring by several: (zenith [deg], azimuths or None for 0, 45,
    ..., 315) per ring, e.g. ``[(29, None), (60, [0, 90, 180, 270])]``. ``region`` = (lo,
    hi) [km] aims the cameras at the centre of that box instead of the medium's, and fits
    the field of view (and the ``nadir`` preset's distance) to it: cameras that look at a
    part of a wide domain. The region need not lie inside the medium.

    ``distance`` [km] is from the box centre; the ``nadir`` preset (a steep ring for domains
    much wider than they are tall) puts the cameras at 1.2 x the box's horizontal
    diagonal, at least 2 km. ``altitude`` [km] instead puts every camera at that height:
    the zenith camera straight above the centre, the ring at ``ring_zenith`` from the
    vertical through the centre (so farther away). ``fov`` [deg] defaults to the one that
    frames the whole box from the nearest camera (:func:`cloudct.mc.cameras.box_fitting_fov`).
    The scene is checked against the box (:func:`check_scene`): cameras inside it, below
    the ground or seeing nothing of it are refused.
    """
    if preset not in PRESETS:
        raise ValueError(f"preset must be one of {sorted(PRESETS)}, got {preset!r}")
    lo = np.asarray(box_min, dtype=float)
    hi = np.asarray(box_max, dtype=float)
    base = PRESETS[preset]
    npix = base["npix"] if npix is None else int(npix)
    if rings is None:
        rings = [(base["ring_zenith"] if ring_zenith is None else ring_zenith, azimuths)]
    elif ring_zenith is not None or azimuths is not None:
        raise ValueError("give rings, or one ring's zenith and azimuths, not both")
    rings = [(float(z), np.arange(0.0, 360.0, 45.0) if a is None else np.asarray(a, float))
             for z, a in rings]
    target_lo, target_hi = (lo, hi) if region is None else (
        np.asarray(region[0], dtype=float), np.asarray(region[1], dtype=float))
    if target_lo.shape != (3,) or target_hi.shape != (3,) or not np.all(target_hi > target_lo):
        raise ValueError(f"region must be (lo, hi) with hi > lo in x, y and z, got {region}")
    centre = 0.5 * (target_lo + target_hi)
    if altitude is not None:
        if distance is not None:
            raise ValueError("give the cameras' distance or their altitude, not both")
        if not altitude > hi[2]:
            raise ValueError(f"altitude {altitude} km is not above the box (top {hi[2]} km)")
        if not all(0.0 <= zenith < 90.0 for zenith, _ in rings):
            raise ValueError("with an altitude the ring zeniths must be in [0, 90), got "
                             f"{[zenith for zenith, _ in rings]}")
        distance = altitude - centre[2]
    elif distance is None:
        distance = base["distance"]
        if distance is None:
            distance = max(2.0, 1.2 * float(np.hypot(*(target_hi - target_lo)[:2])))
    if not distance > 0.0:
        raise ValueError(f"distance must be positive (km), got {distance}")
    if fov is None:
        fov = box_fitting_fov(target_lo, target_hi, distance)
    cameras = ring_cameras(tuple(centre), distance=distance, zenith=0.0, azimuths=[],
                           fov=fov, npix=npix)
    for zenith, ring_azimuths in rings:  # at an altitude, each ring is farther away
        ring_distance = (distance if altitude is None
                         else distance / math.cos(math.radians(zenith)))
        cameras += ring_cameras(tuple(centre), distance=ring_distance, zenith=zenith,
                                azimuths=ring_azimuths, fov=fov, npix=npix,
                                include_zenith=False)
    scene = Scene(cameras=cameras, sun=Sun(sun_zenith, sun_azimuth), boundary=boundary,
                  ground_albedo=ground_albedo)
    check_scene(scene, tuple(np.array([a, b]) for a, b in zip(lo, hi, strict=True)))
    return scene


def corner_rays(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Origins and unit directions (each (4, 3)) of the rays through the image's corners."""
    hw, hh = camera.half_size()
    return camera.rays(np.array([-hw, -hw, hw, hw]), np.array([-hh, hh, -hh, hh]))


def _pixel_rays(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Origins and unit directions of the rays through every pixel centre, each of shape
    (nrows * ncols, 3)."""
    hw, hh = camera.half_size()
    u = -hw + (np.arange(camera.ncols) + 0.5) * 2.0 * hw / camera.ncols
    v = hh - (np.arange(camera.nrows) + 0.5) * 2.0 * hh / camera.nrows
    uu, vv = np.meshgrid(u, v)
    return camera.rays(uu, vv)


def _rays_hit_box(origin: np.ndarray, rays: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Whether any ray from ``origin`` (one point, or one per ray) meets the axis-aligned
    box [lo, hi] (slab test)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (lo - origin) / rays
        t1 = (hi - origin) / rays
    near = np.where(np.isnan(t0), -np.inf, np.minimum(t0, t1)).max(axis=1)
    far = np.where(np.isnan(t1), np.inf, np.maximum(t0, t1)).min(axis=1)
    return bool(np.any((near <= far) & (far > 0.0)))


def check_scene(scene: Scene, edges: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    """Raise ValueError, naming the camera, for a scene that cannot be rendered right."""
    lo = np.array([e[0] for e in edges])
    hi = np.array([e[-1] for e in edges])
    for i, cam in enumerate(scene.cameras):
        pos = np.asarray(cam.position, float)
        if cam.projection == "orthographic":
            _check_image_plane(i, cam, lo, hi, scene.periodic)
        if scene.periodic:
            if lo[2] <= pos[2] <= hi[2]:
                raise ValueError(
                    f"camera {i} at z = {pos[2]} km is inside the periodic medium "
                    f"(z from {lo[2]} to {hi[2]} km)"
                )
        elif np.all((lo <= pos) & (pos <= hi)):
            raise ValueError(f"camera {i} at {tuple(pos)} km is inside the medium's box")
        if scene.ground_albedo is not None and pos[2] < lo[2]:
            raise ValueError(f"camera {i} is below the ground (z = {pos[2]} < {lo[2]} km)")
        origins, rays = _pixel_rays(cam)
        if scene.periodic:
            seen = np.any(np.sign(rays[:, 2]) == np.sign(lo[2] - origins[:, 2]))
        else:
            seen = _rays_hit_box(origins, rays, lo, hi) or _box_corner_in_view(cam, lo, hi)
        if not seen:
            raise ValueError(f"camera {i} does not see the medium: no pixel looks at the box")


def _check_image_plane(
    index: int, camera: Camera, lo: np.ndarray, hi: np.ndarray, periodic: bool
) -> None:
    """An orthographic camera's image rectangle must lie outside the medium: a local
    estimate's transmittance runs to where its ray leaves the medium. With periodic
    boundaries the rectangle lies above (or below) the slab; with open ones the whole box
    lies in front of its plane."""
    forward, _, _ = camera.frame()
    if periodic:
        z = corner_rays(camera)[0][:, 2]
        if not (np.all(z > hi[2]) or np.all(z < lo[2])):
            raise ValueError(
                f"camera {index}'s orthographic image rectangle reaches into the periodic "
                f"slab (corners at z = {np.round(z, 4).tolist()} km, slab from {lo[2]} to "
                f"{hi[2]} km): move it away from the slab"
            )
        return
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])
    depth = (corners - np.asarray(camera.position, float)) @ forward
    if np.any(depth <= 0.0) and np.any(depth > 0.0):  # (all behind: it sees nothing)
        raise ValueError(
            f"camera {index}'s orthographic image plane cuts the medium's box: move the "
            "camera back along its view direction until the whole box lies in front of it"
        )


def _box_corner_in_view(camera: Camera, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Whether a corner of the box projects into the image (a box smaller than a pixel)."""
    forward, right, up = camera.frame()
    hw, hh = camera.half_size()
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])])
    d = corners - np.asarray(camera.position, float)
    depth = d @ forward
    ok = depth > 0
    u = (d @ right)[ok]
    v = (d @ up)[ok]
    if camera.projection == "pinhole":
        u, v = u / depth[ok], v / depth[ok]
    return bool(np.any((np.abs(u) < hw) & (np.abs(v) < hh)))


def periodic_copy_ranges(
    scene: Scene, edges: tuple[np.ndarray, np.ndarray, np.ndarray]
) -> np.ndarray:
    """Range of periodic images (i0, i1, j0, j1) each camera can see, int64[nview, 4].

    The part of the slab inside a camera's view is the convex hull of where its four
    corner rays (pinhole or orthographic) meet the slab's bottom and top planes; the box
    copies i * Lx, j * Ly that overlap it are the ones a local estimate must visit. Open
    boundaries: only (0, 0).
    """
    ranges = np.zeros((len(scene.cameras), 4), dtype=np.int64)
    if not scene.periodic:
        return ranges
    xe, ye, ze = edges
    lx, ly = xe[-1] - xe[0], ye[-1] - ye[0]
    for k, cam in enumerate(scene.cameras):
        origins, rays = corner_rays(cam)
        points = []
        for zp in (ze[0], ze[-1]):
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (zp - origins[:, 2]) / rays[:, 2]
            if np.any(~np.isfinite(t)) or np.any(t <= 0.0):
                raise ValueError(
                    f"camera {k} sees the periodic slab out to the horizon; narrow its field "
                    "of view or tilt it towards the slab"
                )
            points.append(origins[:, :2] + t[:, None] * rays[:, :2])
        pts = np.concatenate(points)
        # copy i holds x + i Lx for x in [x0, x1): it meets [xmin, xmax] for
        # ceil((xmin - x1) / Lx) <= i <= floor((xmax - x0) / Lx)
        ranges[k] = (
            np.ceil((pts[:, 0].min() - xe[-1]) / lx),
            np.floor((pts[:, 0].max() - xe[0]) / lx),
            np.ceil((pts[:, 1].min() - ye[-1]) / ly),
            np.floor((pts[:, 1].max() - ye[0]) / ly),
        )
    return ranges


def load_scene(path: str | os.PathLike) -> Scene:
    """The scene in a netCDF file written by ``cloudct scene`` (:meth:`Scene.to_dataset`);
    a file that cannot be read, or that holds no scene, raises one line naming it."""
    ds = load_netcdf(path, "scene")
    try:
        return Scene.from_dataset(ds)
    except (KeyError, ValueError) as err:
        raise InputFileError(f"scene file {path} holds no valid scene: {err}") from None
