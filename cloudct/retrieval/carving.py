"""Space carving: the cloud's hull from its multi-view images, and the initial medium.

Seed paper Sec. 6.1.1: the retrieval starts from the space-carved hull of the cloud
[Kutulakos and Seitz 2000] filled with the cloud's mean extinction. Here:

1. **Clear-sky background** (:func:`~cloudct.retrieval.cloudy_pixels.clear_sky_background`).
   What a pixel would see without the cloud: sunlight singly scattered by the template's
   air along the pixel's rays through the medium, plus the sunlit Lambertian ground where
   the scene has one.
2. **Cloudy pixels** (:func:`~cloudct.retrieval.cloudy_pixels.cloud_masks`). A pixel is
   cloudy when its radiance exceeds its clear-sky background by more than the larger of a
   fraction of the view's cloud signal and a multiple of the pixel's noise standard
   deviation (or a given threshold).
3. **Votes.** A voxel is projected onto each view with the camera's projection, pinhole
   or orthographic (:func:`~cloudct.retrieval.cloudy_pixels.project_points`, the
   vectorised twin of :func:`cloudct.mc.cameras.project`) at the centres of its sub-cells
   (``subsamples`` per axis).
   View v votes for the voxel when one of those points falls on a cloudy pixel, or when
   one falls outside the image or on a masked (NaN) pixel: a view cannot carve away what
   it does not see. With periodic boundaries a view sees every periodic copy of the voxel
   (shifted by i Lx, j Ly), each along its own line of sight, and a clear line of sight
   through any copy clears the voxel: the view votes only when every copy it can see
   passes the test above (a copy wholly outside the image passes; so when no copy is in
   the image, the view votes).
4. **Hull.** The voxels with at least k votes form the hull. The default k is every view
   but one (n - 1; n when there are fewer than three views): one view may miss a part of
   the cloud, typically a shadowed cloud base seen from the side, which is no brighter
   than the clear sky behind it, or a thin edge lost in the noise.

5. **Profile** (:func:`extinction_profile`). The seed paper fills the hull with a
   constant. By default the hull is filled in proportion to the faintest excess radiance
   in which the views (with periodic boundaries: the copies the views see) see each voxel
   instead: the soft form of the vote, which puts little extinction where some line of
   sight through a voxel sees little cloud light (``profile="constant"`` gives the seed
   paper's start). On the seed paper's single cloud this start
   has epsilon 0.68 against 1.33 for the constant, each at its fitted mean extinction
   (docs/measurements_and_carving.md). ``profile="adiabatic"`` multiplies the excess
   profile by the vertical shape of an adiabatic cloud, (z - z_base)^(2/3) above the hull's
   base (:func:`adiabatic_shape`): liquid water growing linearly with height and the
   droplets' radius as its cube root, which puts less extinction in the hull's lower part,
   where views from above cannot carve (on the two cumuli epsilon 0.72 against 0.78).

:func:`fit_extinction` (called by :func:`carve`) finds the mean extinction that makes the
hull's rendered images as bright as the measurements, and :func:`initial_medium` fills the
hull with the profile scaled to it.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import NamedTuple

import numpy as np
import xarray as xr

from cloudct.mc.backend import resolve_backend
from cloudct.mc.cameras import CameraArrays, camera_arrays
from cloudct.mc.render import render
from cloudct.mc.scene import Scene, check_scene
from cloudct.measurements import validate_measurements
from cloudct.medium import (
    cell_edges,
    optical_medium,
    validate_medium,
)
from cloudct.optics import optics_name, to_optical
from cloudct.retrieval.cloudy_pixels import (
    cell_index,
    cloud_masks,
    medium_bounds,
    pixel_ray_origins,
    pixel_rays,
    project_points,
    ray_box,
    ray_steps,
    view_copies,
    wrapped_index,
)
from cloudct.retrieval.priors import ADIABATIC_EXPONENT

#: Default number of sub-cells per axis at whose centres a voxel is projected.
SUBSAMPLES = 3
#: Shapes of the initial extinction in the hull (see :func:`carve`).
PROFILES = ("excess", "constant", "adiabatic")
#: Absolute tolerance on the measured box, as a fraction of the box's largest extent.
BOX_RTOL = 1e-6
#: Photons of each trial render of :func:`fit_extinction`.
FIT_PHOTONS = 100_000


# ---------------------------------------------------------------------------------------
# Carving
# ---------------------------------------------------------------------------------------


def carve(
    measurements: xr.Dataset,
    grid_template: xr.Dataset,
    *,
    k: int | None = None,
    threshold: float | None = None,
    subsamples: int = SUBSAMPLES,
    profile: str = "excess",
    fit_photons: int | None = FIT_PHOTONS,
    backend: str = "cpu",
) -> xr.Dataset:
    """The space-carved hull of the cloud on the grid of ``grid_template``, and the shape of
    the initial medium's extinction in it.

    Args:
        measurements: a measurement set (images with cameras and sun, see
            :mod:`cloudct.measurements`).
        grid_template: a medium whose grid (x, y, z and z_bounds) the hull is built on and
            whose air gives the clear-sky background. When the measurements record the box
            of the medium they were made of (``medium_box``), the template's box must be
            the same (its resolution may differ).
        k: the number of views that must vote for a voxel (1 <= k <= views); default
            :func:`default_k`.
        threshold: cloudy-pixel threshold [radiance above the clear-sky background];
            default the per-view rule of :func:`cloud_masks`.
        subsamples: sub-cells per axis at whose centres each voxel is projected.
        profile: the shape of the extinction in the hull: ``"excess"``, the soft-carving
            profile of :func:`extinction_profile`, ``"adiabatic"``, that profile times
            :func:`adiabatic_shape`, or ``"constant"`` (the seed paper's).
        fit_photons: photons per trial render of :func:`fit_extinction`, whose result (the
            hull's mean extinction) is stored as the attribute ``extinction_estimate``
            [km-1]; None skips the fit.
        backend: where the fit's renders run (``"cpu"``, ``"cuda"`` or ``"auto"``,
            :mod:`cloudct.mc.backend`); recorded in the attribute ``backend``.

    Returns:
        A Dataset on the template's grid with ``hull`` (x, y, z) int8 (1 inside),
        ``votes`` (x, y, z), ``extinction_profile`` (x, y, z) (the shape, mean 1 in the
        hull, 0 outside), the variables of :func:`cloud_masks`, ``hull_silhouette``
        (view, row, col) int8 (pixels whose centre ray crosses the hull) and the attributes
        ``k``, ``views``, ``subsamples``, ``profile`` and (unless the fit was skipped or the
        hull is empty) ``extinction_estimate``.

    Raises:
        ValueError: a camera inside the box or not seeing it, a template box different
            from the measured medium's, a bad k, subsamples or profile, or an excess
            profile that is zero in the whole hull.
    """
    validate_measurements(measurements)
    validate_medium(grid_template)
    edges = cell_edges(grid_template)
    _check_box(measurements, edges)
    scene = Scene.from_dataset(measurements)
    check_scene(scene, edges)
    nview = len(scene.cameras)
    k = default_k(nview) if k is None else int(k)
    if not 1 <= k <= nview:
        raise ValueError(f"k must be between 1 and the number of views ({nview}), got {k}")
    if int(subsamples) < 1:
        raise ValueError(f"subsamples must be >= 1, got {subsamples}")
    if profile not in PROFILES:
        raise ValueError(f"profile must be one of {PROFILES}, got {profile!r}")

    masks = cloud_masks(measurements, grid_template, threshold)
    views = _Views(camera_arrays(scene.cameras), view_copies(scene, edges))
    observed = np.isfinite(measurements["radiance"].values)
    votes = _votes(views, masks["cloud_mask"].values.astype(bool), observed, edges,
                   int(subsamples))
    hull = votes >= k
    if profile != "constant" and hull.any():
        excess = measurements["radiance"].values - masks["clear_sky_radiance"].values
        shape = extinction_profile(_faintest_excess(views, excess, edges, int(subsamples)),
                                   hull)
        if profile == "adiabatic":
            shape = shape * adiabatic_shape(hull, edges[2])
            shape /= shape[hull].mean()
    else:
        shape = hull.astype(float)

    grid = ("x", "y", "z")
    ds = masks.assign_coords({name: grid_template[name] for name in grid})
    if "z_bounds" in grid_template:
        ds["z_bounds"] = grid_template["z_bounds"]
    ds["hull"] = (grid, hull.astype(np.int8), {
        "units": "1", "long_name": "space-carved cloud hull (1 inside)"})
    ds["votes"] = (grid, votes, {
        "units": "1", "long_name": "views seeing the voxel as cloudy or not seeing it"})
    ds["extinction_profile"] = (grid, shape, {
        "units": "1", "long_name": f"{profile} shape of the initial extinction (mean 1 in "
        "the hull)"})
    ds["hull_silhouette"] = (("view", "row", "col"), _silhouette(scene, hull, edges), {
        "units": "1", "long_name": "pixel whose centre ray crosses the hull"})
    ds.attrs.update(
        title="cloudct space-carved hull", Conventions="CF-1.8", k=k, views=nview,
        subsamples=int(subsamples), profile=profile,
    )
    if fit_photons and hull.any():
        ds.attrs["backend"] = resolve_backend(backend)
        ds.attrs["extinction_estimate"] = fit_extinction(
            measurements, ds, grid_template, photons=fit_photons, backend=ds.attrs["backend"]
        )
        ds.attrs["extinction_estimate_units"] = "km-1"
    return ds


def default_k(views: int) -> int:
    """The default vote count of the hull: every view but one, or every view when there are
    fewer than three."""
    return views - 1 if views >= 3 else views


def _check_box(measurements: xr.Dataset, edges: tuple[np.ndarray, ...]) -> None:
    """The template's box must be the one the measurements were made of (when recorded)."""
    if "medium_box" not in measurements.attrs:
        return
    measured = np.asarray(measurements.attrs["medium_box"], dtype=float).ravel()
    template = np.array([v for e in edges for v in (e[0], e[-1])])
    tolerance = BOX_RTOL * float(np.max(template[1::2] - template[::2]))
    if measured.shape != (6,) or not np.allclose(measured, template, rtol=0.0, atol=tolerance):
        raise ValueError(
            f"the template grid's box (x, y, z ranges {_ranges(template)} km) differs from "
            f"the box of the medium the measurements were made of ({_ranges(measured)} km)"
        )


def _ranges(box: np.ndarray) -> str:
    return ", ".join(f"{box[i]:.4g}..{box[i + 1]:.4g}" for i in range(0, len(box) - 1, 2))


class _Views(NamedTuple):
    """The cameras and, per view, the shifts of the periodic copies of the box it can see
    (:func:`~cloudct.retrieval.cloudy_pixels.view_copies`)."""

    cams: CameraArrays
    copies: list[np.ndarray]


def _layer_pixels(
    views: _Views, edges: tuple[np.ndarray, np.ndarray, np.ndarray], nsub: int
) -> Iterator[tuple[int, int, Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]]]:
    """``(kz, view, copies)`` for every z layer and view; ``copies`` yields, for each copy
    of the box the view can see (one with open boundaries), ``(inside, row, col)``: the
    pixels seen by the centres of the ``nsub``^3 sub-cells of the layer's voxels in that
    copy, arrays [nx, ny, nsub, nsub, nsub] (``inside``: the point is in the image; row and
    col are 0 where it is not, so that they index safely). One z layer and one copy at a
    time, to bound the memory."""
    fractions = (np.arange(nsub) + 0.5) / nsub
    sx, sy, sz = (e[:-1, None] + fractions * np.diff(e)[:, None] for e in edges)

    def copies(v: int, points: np.ndarray) -> Iterator[tuple[np.ndarray, ...]]:
        for shift in views.copies[v]:
            row, col = project_points(views.cams, v, points + shift)
            inside = row >= 0
            yield inside, np.where(inside, row, 0), np.where(inside, col, 0)

    for kz in range(len(sz)):
        # points[i, j, a, b, c]: sub-centre a of x cell i, b of y cell j, c of this layer
        px, py, pz = sx[:, None, :, None, None], sy[None, :, None, :, None], sz[kz]
        points = np.stack(np.broadcast_arrays(px, py, pz[None, None, None, None, :]), axis=-1)
        for v in range(len(views.copies)):
            yield kz, v, copies(v, points)


def _votes(
    views: _Views,
    cloudy: np.ndarray,
    observed: np.ndarray,
    edges: tuple[np.ndarray, np.ndarray, np.ndarray],
    nsub: int,
) -> np.ndarray:
    """Votes per voxel, int16[nx, ny, nz] (the rule is in the module docstring)."""
    votes = np.zeros(tuple(len(e) - 1 for e in edges), dtype=np.int16)
    for kz, v, copies in _layer_pixels(views, edges, nsub):
        vote = np.ones(votes.shape[:2], dtype=bool)
        for inside, row, col in copies:
            vote &= (~inside | cloudy[v, row, col] | ~observed[v, row, col]).any(axis=(2, 3, 4))
        votes[:, :, kz] += vote
    return votes


def _faintest_excess(
    views: _Views,
    excess: np.ndarray,
    edges: tuple[np.ndarray, np.ndarray, np.ndarray],
    nsub: int,
) -> np.ndarray:
    """float64[nx, ny, nz]: the smallest, over the views that see a voxel and the periodic
    copies of it they see, of the excess radiance averaged over the (non-NaN) pixels of the
    copy's sub-cell centres; +inf where no view sees the voxel."""
    faintest = np.full(tuple(len(e) - 1 for e in edges), np.inf)
    for kz, v, copies in _layer_pixels(views, edges, nsub):
        for inside, row, col in copies:
            pixel = excess[v, row, col]
            seen = inside & np.isfinite(pixel)
            count = seen.sum(axis=(2, 3, 4))
            with np.errstate(invalid="ignore", divide="ignore"):
                mean = np.where(seen, pixel, 0.0).sum(axis=(2, 3, 4)) / count
            faintest[:, :, kz] = np.minimum(faintest[:, :, kz],
                                            np.where(count > 0, mean, np.inf))
    return faintest


def extinction_profile(faintest: np.ndarray, hull: np.ndarray) -> np.ndarray:
    """The soft-carving shape of the cloud's extinction in the hull, mean 1 there, 0 outside:
    proportional to the faintest excess radiance in which the views see a voxel
    (:func:`_faintest_excess`, negative excess counted as 0).

    Space carving keeps a voxel that every view sees as cloudy; its soft form weighs the
    voxel by how faint the cloud is in the view that sees it faintest, since a voxel cannot
    hold much cloud where some view through it sees little cloud light. Hull voxels that
    no view sees get the mean of the others.

    Raises:
        ValueError: the profile is zero throughout the hull (every hull voxel is seen
            without excess radiance by some view).
    """
    seen = hull & np.isfinite(faintest)
    weight = np.clip(np.where(seen, faintest, 0.0), 0.0, None)
    if not weight.any():
        raise ValueError(
            "no hull voxel is brighter than the clear sky in every view that sees it: the "
            "excess profile is zero (use profile='constant')"
        )
    weight[hull & ~seen] = weight[seen].mean()
    return weight / weight[hull].mean()


def adiabatic_shape(hull: np.ndarray, z_edges: np.ndarray) -> np.ndarray:
    """(z - z_base)^(2/3) at the cell centres, z_base the lower edge of the hull's lowest
    level: an adiabatic cloud's extinction against height (liquid water linear in height,
    the effective radius its cube root: :data:`cloudct.retrieval.priors.ADIABATIC_EXPONENT`),
    0 outside the hull."""
    base = z_edges[np.argmax(hull.any(axis=(0, 1)))]
    height = np.maximum(0.5 * (z_edges[:-1] + z_edges[1:]) - base, 0.0)
    return np.where(hull, height[None, None, :] ** ADIABATIC_EXPONENT, 0.0)


def _silhouette(
    scene: Scene, hull: np.ndarray, edges: tuple[np.ndarray, np.ndarray, np.ndarray]
) -> np.ndarray:
    """int8[view, row, col]: 1 where the pixel's centre ray crosses a hull voxel (marched
    at steps of a quarter of the smallest cell size; through the whole slab, wrapped
    across the side faces, with periodic boundaries)."""
    cams = camera_arrays(scene.cameras)
    lo, hi = medium_bounds(scene, edges)
    index_along = [wrapped_index if scene.periodic and axis < 2 else cell_index
                   for axis in range(3)]
    step = 0.25 * min(float(np.diff(e).min()) for e in edges)
    out = np.zeros((cams.position.shape[0], cams.nrows, cams.ncols), dtype=np.int8)
    for v in range(out.shape[0]):
        origins = pixel_ray_origins(cams, v)[:, :, 0]
        rays = pixel_rays(cams, v)[:, :, 0]
        t_in, t_out = ray_box(origins, rays, lo, hi)
        hit = np.zeros(t_in.shape, dtype=bool)
        for live, t, _ in ray_steps(t_in, t_out, step):
            point = origins[live] + t[:, None] * rays[live]
            index = tuple(index_along[a](e, point[:, a]) for a, e in enumerate(edges))
            hit[live] |= hull[index]
        out[v] = hit
    return out


# ---------------------------------------------------------------------------------------
# The initial medium
# ---------------------------------------------------------------------------------------


def fit_extinction(
    measurements: xr.Dataset,
    carved: xr.Dataset,
    template_medium: xr.Dataset,
    *,
    photons: int = FIT_PHOTONS,
    seed: int = 0,
    rtol: float = 0.01,
    max_iterations: int = 12,
    backend: str = "cpu",
) -> float:
    """The hull's mean cloud extinction [km-1] whose images are as bright as the
    measurements, the hull being filled in the carved ``extinction_profile`` (constant
    for a bare hull mask); the renders run on ``backend`` (:mod:`cloudct.mc.backend`).

    The summed radiance of all measured (non-NaN) pixels, B*, is matched by the summed
    radiance B(beta) of :func:`initial_medium` renders (forward, ``photons`` photons, the
    same ``seed`` every time so that B varies smoothly with beta). The root of
    log B(beta) = log B* is found by the secant method in log beta from 5 and 20 km-1,
    steps limited to a factor of 4 and beta to 10^-3 .. 10^4 km-1, until B matches B* to
    ``rtol``. With a constant profile this is the best
    constant in the seed paper's sense of "the average extinction of the cloud" as the
    forward model sees it: it accounts for the light a finite cloud loses through its sides,
    which a plane-parallel relation would not.

    Raises:
        ValueError: no extinction matches within ``max_iterations`` renders (for instance
            measurements no brighter than the clear sky, or a hull too small to be as
            bright as the cloud).
    """
    measured = measurements["radiance"].values
    observed = np.isfinite(measured)
    target = float(measured[observed].sum())
    scene = Scene.from_dataset(measurements)

    def log_ratio(log_beta: float) -> float:
        medium = initial_medium(carved, template_medium, math.exp(log_beta))
        images = render(medium, scene, photons=photons, seed=seed, progress=False,
                        backend=backend)
        return math.log(float(images["radiance"].values[observed].sum()) / target)

    x0, x1 = math.log(5.0), math.log(20.0)
    f0, f1 = log_ratio(x0), log_ratio(x1)
    for _ in range(max_iterations):
        if abs(f1) <= rtol:
            return math.exp(x1)
        slope = (f1 - f0) / (x1 - x0) if f1 != f0 else 1.0
        step = float(np.clip(-f1 / max(slope, 1e-3), -math.log(4.0), math.log(4.0)))
        x0, f0 = x1, f1
        x1 = float(np.clip(x1 + step, math.log(1.0e-3), math.log(1.0e4)))
        f1 = log_ratio(x1)
    if abs(f1) <= rtol:
        return math.exp(x1)
    hull = int(np.count_nonzero(carved["hull"] if isinstance(carved, xr.Dataset) else carved))
    why = (
        f"the hull's {hull} voxels are too few to be as bright as the cloud: its cloudy-pixel "
        "masks are probably too strict or too noisy (measurements of more photons, a lower "
        "threshold or a smaller k keep more voxels)" if f1 < 0.0 else
        "even a nearly empty hull renders brighter than the measurements (measurements no "
        "brighter than the clear sky, or the wrong optics, sun or ground)"
    )
    raise ValueError(
        f"no hull extinction matches the measured brightness (last {math.exp(x1):.4g} km-1 "
        f"off by {100 * (math.exp(f1) - 1):+.1f} %): {why}"
    )


def initial_medium(
    carved: xr.Dataset | xr.DataArray,
    template_medium: xr.Dataset,
    extinction: float | None = None,
) -> xr.Dataset:
    """The retrieval's initial medium: the hull filled with the carved extinction profile
    (constant for a bare hull mask) scaled to a mean extinction, zero outside.

    Args:
        carved: the result of :func:`carve`, or a hull mask (x, y, z) on the template's
            grid (filled with a constant extinction).
        template_medium: gives the grid and the air (kept as they are) and the cloud
            albedo and phase function (HG g, or the tabulated phase functions with their
            per-cell index); a microphysical template is given its optics first
            (:func:`cloudct.optics.to_optical`: its recorded choice, else the default).
        extinction: the mean cloud extinction in the hull [km-1]; default the
            ``extinction_estimate`` that :func:`carve` stored (:func:`fit_extinction`).

    Returns:
        A validated optical medium.

    Raises:
        ValueError: grids that differ, an empty hull, or a missing or negative extinction.
    """
    validate_medium(template_medium)
    template_medium = to_optical(template_medium)
    mask = carved["hull"] if isinstance(carved, xr.Dataset) else carved
    if extinction is None:
        if "extinction_estimate" not in carved.attrs:
            raise ValueError("give the extinction: the hull carries no extinction_estimate")
        extinction = float(carved.attrs["extinction_estimate"])
    if not (math.isfinite(extinction) and extinction >= 0.0):
        raise ValueError(f"extinction must be finite and >= 0, got {extinction}")
    for name in ("x", "y", "z"):
        if (
            name not in mask.coords
            or mask.sizes[name] != template_medium.sizes[name]
            or not np.allclose(mask[name].values, template_medium[name].values, rtol=1e-9)
        ):
            raise ValueError(f"the hull's grid differs from the template's along {name}")
    hull = mask.transpose("x", "y", "z").values.astype(bool)
    if not hull.any():
        raise ValueError("the hull is empty: nothing to fill (lower the threshold or k)")
    shape, profile = hull.astype(float), "constant"
    if isinstance(carved, xr.Dataset) and "extinction_profile" in carved:
        shape = carved["extinction_profile"].transpose("x", "y", "z").values
        profile = carved.attrs.get("profile", "given")

    cloud = {"cloud_albedo": template_medium["cloud_albedo"]}
    if "cloud_g" in template_medium:
        cloud["cloud_g"] = template_medium["cloud_g"]
    else:
        table = template_medium["cloud_phase"]
        cloud["cloud_phase"] = (table.values, table["scattering_angle"].values)
        cloud["cloud_phase_index"] = template_medium["cloud_phase_index"]
        if "cloud_phase_weight" in template_medium:
            cloud["cloud_phase_weight"] = template_medium["cloud_phase_weight"]
    medium = optical_medium(
        template_medium["x"].values,
        template_medium["y"].values,
        template_medium["z"].values,
        np.where(hull, extinction * shape, 0.0),
        air_extinction=template_medium["air_extinction"],
        air_albedo=float(template_medium["air_albedo"]),
        z_bounds=template_medium["z_bounds"].values if "z_bounds" in template_medium else None,
        wavelength=template_medium.attrs.get("wavelength"),
        title="cloudct initial medium (space-carved hull)",
        source=f"cloudct.retrieval.carving.initial_medium, {profile} profile, mean "
        f"extinction {extinction:.6g} km-1",
        **cloud,
    )
    medium = medium.assign_attrs(optics=optics_name(template_medium))
    if isinstance(carved, xr.Dataset) and "backend" in carved.attrs:
        medium.attrs["carving_backend"] = carved.attrs["backend"]  # where the fit ran
    return medium
