"""Space carving: the cloud's hull from its multi-view images, and the initial medium.

Seed paper Sec. 6.1.1: the retrieval starts from the space-carved hull of the cloud
[Kutulakos and Seitz 2000] filled with the cloud's mean extinction. Here:

1. **Clear-sky background** (:func:`clear_sky_background`). What a pixel would see without
   the cloud: sunlight singly scattered by the template's air along the pixel's rays
   through the medium, plus the sunlit Lambertian ground where the scene has one.
2. **Cloudy pixels** (:func:`cloud_masks`). A pixel is cloudy when its radiance exceeds its
   clear-sky background by more than the larger of a fraction of the view's cloud signal
   and a multiple of the pixel's noise standard deviation (or a given threshold).
3. **Votes.** A voxel is projected onto each view with the cameras' pinhole model
   (:func:`project_points`, the vectorised twin of :func:`cloudct.mc.cameras.project`) at
   the centres of its ``subsamples``^3 sub-cells. View v votes for the voxel when one of
   those points falls on a cloudy pixel, or when one falls outside the image or on a masked
   (NaN) pixel: a view cannot carve away what it does not see.
4. **Hull.** The voxels with at least k votes form the hull. The default k is every view
   but one (n - 1; n when there are fewer than three views): one view may miss a part of
   the cloud, typically a shadowed cloud base seen from the side, which is no brighter
   than the clear sky behind it, or a thin edge lost in the noise.

5. **Profile** (:func:`extinction_profile`). The seed paper fills the hull with a
   constant. By default the hull is filled in proportion to the faintest excess radiance
   in which the views see each voxel instead: the soft form of the vote, which puts little
   extinction where some view through a voxel sees little cloud light (``profile=
   "constant"`` gives the seed paper's start). On the seed paper's single cloud this start
   has epsilon 0.68 against 1.33 for the constant, each at its fitted mean extinction
   (docs/measurements_and_carving.md).

:func:`fit_extinction` (called by :func:`carve`) finds the mean extinction that makes the
hull's rendered images as bright as the measurements, and :func:`initial_medium` fills the
hull with the profile scaled to it.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import xarray as xr

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

#: Default cloudy-pixel rule (see :func:`cloud_masks`).
SIGNAL_FRACTION = 0.02
SIGNAL_PERCENTILE = 99.0
NOISE_MULTIPLE = 3.0
#: Default number of sub-cells per axis at whose centres a voxel is projected.
SUBSAMPLES = 3
#: Shapes of the initial extinction in the hull (see :func:`carve`).
PROFILES = ("excess", "constant")
#: Sub-pixel rays per axis of the clear-sky background.
BACKGROUND_SUBPIXELS = 4
#: Absolute tolerance on the measured box, as a fraction of the box's largest extent.
BOX_RTOL = 1e-6
#: Photons of each trial render of :func:`fit_extinction`.
FIT_PHOTONS = 100_000


# ---------------------------------------------------------------------------------------
# Geometry: projection and rays
# ---------------------------------------------------------------------------------------


def project_points(
    cams: CameraArrays, view: int, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (row, col) of camera ``view`` seeing ``points`` (..., 3) [km]; -1 where a
    point is behind the camera or outside the image. The vectorised twin of
    :func:`cloudct.mc.cameras.project` (the same pinhole model and pixel edges)."""
    d = points - cams.position[view]
    depth = d @ cams.forward[view]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (d @ cams.right[view]) / depth
        v = (d @ cams.up[view]) / depth
    hw, hh = cams.half_width[view], cams.half_height[view]
    inside = (depth > 0.0) & (-hw <= u) & (u < hw) & (-hh < v) & (v <= hh)
    col = np.minimum(np.floor((u + hw) / (2.0 * hw) * cams.ncols), cams.ncols - 1)
    row = np.minimum(np.floor((hh - v) / (2.0 * hh) * cams.nrows), cams.nrows - 1)
    return np.where(inside, row, -1).astype(np.int64), np.where(inside, col, -1).astype(np.int64)


def pixel_rays(cams: CameraArrays, view: int, subpixels: int = 1) -> np.ndarray:
    """Unit directions from the pinhole of ``view`` through the centres of the
    ``subpixels`` x ``subpixels`` sub-pixels of every pixel, (nrows, ncols, subpixels^2, 3)
    (the same image plane as :func:`cloudct.mc.cameras.pixel_ray`)."""
    hw, hh = cams.half_width[view], cams.half_height[view]
    offsets = (np.arange(subpixels) + 0.5) / subpixels
    u = -hw + (np.arange(cams.ncols)[:, None] + offsets).ravel() * (2.0 * hw / cams.ncols)
    v = hh - (np.arange(cams.nrows)[:, None] + offsets).ravel() * (2.0 * hh / cams.nrows)
    rays = (
        cams.forward[view]
        + u[None, :, None] * cams.right[view]
        + v[:, None, None] * cams.up[view]
    )
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    # (nrows * s, ncols * s, 3) -> (nrows, ncols, s * s, 3)
    s = subpixels
    rays = rays.reshape(cams.nrows, s, cams.ncols, s, 3).transpose(0, 2, 1, 3, 4)
    return rays.reshape(cams.nrows, cams.ncols, s * s, 3)


def ray_box(
    origin: np.ndarray, rays: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Distances (t_in, t_out) along ``rays`` (..., 3) from ``origin`` through the box
    [lo, hi] (slab method; infinite bounds allowed). t_in >= t_out where a ray misses."""
    # a ray parallel to a pair of faces gets +-inf there (inside the slab for every t, or
    # never), or NaN (0/0) when it runs in a face plane: counted as inside
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (lo - origin) / rays
        t1 = (hi - origin) / rays
    near = np.where(np.isnan(t0), -np.inf, np.minimum(t0, t1))
    far = np.where(np.isnan(t1), np.inf, np.maximum(t0, t1))
    return np.maximum(near.max(axis=-1), 0.0), far.min(axis=-1)


def _march(
    t_in: np.ndarray, t_out: np.ndarray, step: float
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Steps along rays from t_in to t_out: yields (live, midpoint t, segment length), the
    last segment of each ray cut at t_out."""
    start = t_in.copy()
    while np.any(live := start < t_out):
        end = np.minimum(start[live] + step, t_out[live])
        yield live, 0.5 * (start[live] + end), end - start[live]
        start[live] = end


def _cell_index(edges: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Index of the cell of ``edges`` holding each value (clamped to the grid)."""
    return np.clip(np.searchsorted(edges, values, side="right") - 1, 0, len(edges) - 2)


def _box(edges: tuple[np.ndarray, ...]) -> tuple[np.ndarray, np.ndarray]:
    return np.array([e[0] for e in edges]), np.array([e[-1] for e in edges])


# ---------------------------------------------------------------------------------------
# Clear-sky background and cloudy pixels
# ---------------------------------------------------------------------------------------


def clear_sky_background(
    scene: Scene, template: xr.Dataset, subpixels: int = BACKGROUND_SUBPIXELS
) -> np.ndarray:
    """Radiance each pixel would see without the cloud, float64[view, row, col].

    Single scattering of sunlight by the template's air, averaged over
    ``subpixels`` x ``subpixels`` rays per pixel:

        L_air = w_air p_R(Theta) integral beta_air(z) T_sun(z) T_view(t) dt

    along the ray inside the medium (the box; with periodic boundaries the whole slab),
    with p_R the Rayleigh phase function at the scattering angle Theta between the sun's
    rays and the direction to the camera, beta_air the air extinction averaged over x and y,
    T_view the transmittance back to the camera and T_sun = exp(-tau_above(z) / mu0) that
    from the top of the medium. A Lambertian ground of albedo A seen by the ray adds
    A mu0 / pi T_sun(ground) T_view(ground). Air multiple scattering and sunlight entering
    through the side faces (open boundaries, oblique sun) are neglected: errors of the order
    of the air's optical depth (a few per cent) in a background that is itself small.
    """
    validate_medium(template)
    edges = cell_edges(template)
    check_scene(scene, edges)
    z_edges = edges[2]
    air = template["air_extinction"]
    beta = np.broadcast_to(
        air.mean(dim=[d for d in air.dims if d != "z"]).values, (len(z_edges) - 1,)
    )
    tau_below = np.concatenate(([0.0], np.cumsum(beta * np.diff(z_edges))))
    albedo = float(template["air_albedo"])
    sun = scene.sun.travel_direction()
    mu0 = -sun[2]

    def sun_transmittance(z: np.ndarray) -> np.ndarray:
        tau_above = tau_below[-1] - np.interp(z, z_edges, tau_below)
        return np.exp(-tau_above / mu0)

    lo, hi = _box(edges)
    if scene.periodic:
        lo[:2], hi[:2] = -np.inf, np.inf
    step = 0.5 * float(np.diff(z_edges).min())
    cams = camera_arrays(scene.cameras)
    out = np.zeros((len(scene.cameras), cams.nrows, cams.ncols))
    for v in range(out.shape[0]):
        origin = cams.position[v]
        rays = pixel_rays(cams, v, subpixels)
        t_in, t_out = ray_box(origin, rays, lo, hi)
        mu = -(rays @ sun)  # cos(scattering angle): sun's rays vs. direction to the camera
        phase = 3.0 / (16.0 * np.pi) * (1.0 + mu * mu)
        radiance = np.zeros(t_in.shape)
        tau_view = np.zeros(t_in.shape)
        for live, t, length in _march(t_in, t_out, step):
            z = origin[2] + t * rays[live][:, 2]
            b = beta[_cell_index(z_edges, z)]
            radiance[live] += (
                b * length * np.exp(-(tau_view[live] + 0.5 * b * length)) * sun_transmittance(z)
            )
            tau_view[live] += b * length
        radiance *= albedo * phase
        if scene.ground_albedo is not None:
            ground = (t_in < t_out) & (
                np.abs(origin[2] + t_out * rays[..., 2] - z_edges[0]) <= 1e-9 + 1e-9 * t_out
            )
            radiance += np.where(
                ground,
                scene.ground_albedo * mu0 / np.pi * sun_transmittance(z_edges[0])
                * np.exp(-tau_view),
                0.0,
            )
        out[v] = radiance.mean(axis=-1)
    return out


def cloud_masks(
    measurements: xr.Dataset, template: xr.Dataset, threshold: float | None = None
) -> xr.Dataset:
    """Cloudy pixels of every view.

    The excess e = L - L_clear of each pixel over its clear-sky background
    (:func:`clear_sky_background`) is cloudy when

        e > max(SIGNAL_FRACTION * e_peak,v, NOISE_MULTIPLE * sigma),

    with e_peak,v the ``SIGNAL_PERCENTILE`` (99th) percentile of the excess over the view's
    pixels that look into the medium (its cloud signal), sigma the pixel's
    ``radiance_noise_std`` (else ``radiance_std_error``, else 0), SIGNAL_FRACTION = 0.02
    and NOISE_MULTIPLE = 3. The noise term keeps noise out; the fraction term is a floor for
    measurements with small or no noise estimates (it covers the error of the clear-sky
    model, 1-2.5 % of the air's radiance, and air lit by the cloud). A given ``threshold``
    [radiance units] replaces the rule in every view. NaN pixels are never cloudy.

    Returns:
        A Dataset with ``cloud_mask`` (view, row, col) int8 (1 cloudy),
        ``clear_sky_radiance`` (view, row, col) and ``signal_threshold`` (view), the
        fraction term of the rule (or the given threshold).
    """
    radiance = measurements["radiance"].values
    sigma = np.zeros_like(radiance)
    for name in ("radiance_noise_std", "radiance_std_error"):
        if name in measurements:
            sigma = measurements[name].values
            break
    scene = Scene.from_dataset(measurements)
    background = clear_sky_background(scene, template)
    excess = radiance - background
    lo, hi = _box(cell_edges(template))
    if scene.periodic:
        lo[:2], hi[:2] = -np.inf, np.inf
    cams = camera_arrays(scene.cameras)
    signal = np.zeros(radiance.shape[0])
    mask = np.zeros(radiance.shape, dtype=bool)
    for v in range(radiance.shape[0]):
        if threshold is None:
            t_in, t_out = ray_box(cams.position[v], pixel_rays(cams, v)[:, :, 0], lo, hi)
            seen = excess[v][(t_in < t_out) & np.isfinite(excess[v])]
            if seen.size:
                signal[v] = SIGNAL_FRACTION * max(np.percentile(seen, SIGNAL_PERCENTILE), 0.0)
            pixel_threshold = np.maximum(signal[v], NOISE_MULTIPLE * sigma[v])
        else:
            signal[v] = pixel_threshold = float(threshold)
        with np.errstate(invalid="ignore"):
            mask[v] = excess[v] > pixel_threshold
    dims = ("view", "row", "col")
    rule = (
        f"radiance above the clear-sky background by more than max({SIGNAL_FRACTION:g} x "
        f"the view's p{SIGNAL_PERCENTILE:g} excess, {NOISE_MULTIPLE:g} x the pixel's noise "
        "std)" if threshold is None else f"radiance above the clear-sky background by more "
        f"than {threshold:g}"
    )
    return xr.Dataset(
        {
            "cloud_mask": (dims, mask.astype(np.int8), {
                "units": "1", "long_name": "pixel judged cloudy (1) or clear (0)",
                "comment": rule}),
            "clear_sky_radiance": (dims, background, {
                "units": "1", "long_name": "clear-sky background radiance (air, ground)"}),
            "signal_threshold": ("view", signal, {
                "units": "1", "long_name": "cloudy-pixel threshold above the background "
                "(before the noise term)"}),
        },
        coords={"view": measurements["view"].values},
    )


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
            profile of :func:`extinction_profile`, or ``"constant"`` (the seed paper's).
        fit_photons: photons per trial render of :func:`fit_extinction`, whose result (the
            hull's mean extinction) is stored as the attribute ``extinction_estimate``
            [km-1]; None skips the fit.

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
    cams = camera_arrays(scene.cameras)
    observed = np.isfinite(measurements["radiance"].values)
    votes = _votes(cams, masks["cloud_mask"].values.astype(bool), observed, edges,
                   int(subsamples))
    hull = votes >= k
    if profile == "excess" and hull.any():
        excess = measurements["radiance"].values - masks["clear_sky_radiance"].values
        shape = extinction_profile(_faintest_excess(cams, excess, edges, int(subsamples)), hull)
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
    ds["hull_silhouette"] = (("view", "row", "col"), _silhouette(cams, hull, edges), {
        "units": "1", "long_name": "pixel whose centre ray crosses the hull"})
    ds.attrs.update(
        title="cloudct space-carved hull", Conventions="CF-1.8", k=k, views=nview,
        subsamples=int(subsamples), profile=profile,
    )
    if fit_photons and hull.any():
        ds.attrs["extinction_estimate"] = fit_extinction(
            measurements, ds, grid_template, photons=fit_photons
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


def _layer_pixels(
    cams: CameraArrays, edges: tuple[np.ndarray, np.ndarray, np.ndarray], nsub: int
) -> Iterator[tuple[int, int, np.ndarray, np.ndarray, np.ndarray]]:
    """``(kz, view, inside, row, col)`` for every z layer and view: the pixels seen by the
    centres of the ``nsub``^3 sub-cells of the layer's voxels, arrays [nx, ny, nsub, nsub,
    nsub] (``inside``: the point is in the image; row and col are 0 where it is not, so
    that they index safely). One z layer at a time, to bound the memory."""
    fractions = (np.arange(nsub) + 0.5) / nsub
    sx, sy, sz = (e[:-1, None] + fractions * np.diff(e)[:, None] for e in edges)
    for kz in range(len(sz)):
        # points[i, j, a, b, c]: sub-centre a of x cell i, b of y cell j, c of this layer
        px, py, pz = sx[:, None, :, None, None], sy[None, :, None, :, None], sz[kz]
        points = np.stack(np.broadcast_arrays(px, py, pz[None, None, None, None, :]), axis=-1)
        for v in range(cams.position.shape[0]):
            row, col = project_points(cams, v, points)
            inside = row >= 0
            yield kz, v, inside, np.where(inside, row, 0), np.where(inside, col, 0)


def _votes(
    cams: CameraArrays,
    cloudy: np.ndarray,
    observed: np.ndarray,
    edges: tuple[np.ndarray, np.ndarray, np.ndarray],
    nsub: int,
) -> np.ndarray:
    """Votes per voxel, int16[nx, ny, nz] (the rule is in the module docstring)."""
    votes = np.zeros(tuple(len(e) - 1 for e in edges), dtype=np.int16)
    for kz, v, inside, row, col in _layer_pixels(cams, edges, nsub):
        vote = ~inside | cloudy[v, row, col] | ~observed[v, row, col]
        votes[:, :, kz] += vote.any(axis=(2, 3, 4))
    return votes


def _faintest_excess(
    cams: CameraArrays,
    excess: np.ndarray,
    edges: tuple[np.ndarray, np.ndarray, np.ndarray],
    nsub: int,
) -> np.ndarray:
    """float64[nx, ny, nz]: the smallest, over the views that see a voxel, of the view's
    excess radiance averaged over the (non-NaN) pixels of the voxel's sub-cell centres;
    +inf where no view sees the voxel."""
    faintest = np.full(tuple(len(e) - 1 for e in edges), np.inf)
    for kz, v, inside, row, col in _layer_pixels(cams, edges, nsub):
        pixel = excess[v, row, col]
        seen = inside & np.isfinite(pixel)
        count = seen.sum(axis=(2, 3, 4))
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(seen, pixel, 0.0).sum(axis=(2, 3, 4)) / count
        faintest[:, :, kz] = np.minimum(faintest[:, :, kz], np.where(count > 0, mean, np.inf))
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


def _silhouette(
    cams: CameraArrays, hull: np.ndarray, edges: tuple[np.ndarray, np.ndarray, np.ndarray]
) -> np.ndarray:
    """int8[view, row, col]: 1 where the pixel's centre ray crosses a hull voxel (marched
    at steps of a quarter of the smallest cell size)."""
    lo, hi = _box(edges)
    step = 0.25 * min(float(np.diff(e).min()) for e in edges)
    out = np.zeros((cams.position.shape[0], cams.nrows, cams.ncols), dtype=np.int8)
    for v in range(out.shape[0]):
        origin = cams.position[v]
        rays = pixel_rays(cams, v)[:, :, 0]
        t_in, t_out = ray_box(origin, rays, lo, hi)
        hit = np.zeros(t_in.shape, dtype=bool)
        for live, t, _ in _march(t_in, t_out, step):
            point = origin + t[:, None] * rays[live]
            index = tuple(_cell_index(e, point[:, a]) for a, e in enumerate(edges))
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
) -> float:
    """The hull's mean cloud extinction [km-1] whose images are as bright as the
    measurements, the hull being filled in the carved ``extinction_profile`` (constant
    for a bare hull mask).

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
        images = render(medium, scene, photons=photons, seed=seed, progress=False)
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
    raise ValueError(
        f"no hull extinction matches the measured brightness (last {math.exp(x1):.4g} km-1 "
        f"off by {100 * (math.exp(f1) - 1):+.1f} %)"
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
    return medium.assign_attrs(optics=optics_name(template_medium))


# ---------------------------------------------------------------------------------------
# Figure and command line
# ---------------------------------------------------------------------------------------


def save_hull_figure(carved: xr.Dataset, measurements: xr.Dataset, path: str | Path) -> Path:
    """Every view's measured image with the outlines of its cloudy pixels (cyan) and of the
    hull's silhouette (red), and below them the hull's extinction profile summed along z, y
    and x (top and side views, km). Returns the path written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    radiance = measurements["radiance"].values
    nview = radiance.shape[0]
    ncol = max(math.ceil(math.sqrt(nview)), 3)
    nrow = math.ceil(nview / ncol) + 1  # the last row: the profile
    vmax = float(np.nanmax(radiance)) or 1.0
    fig, axes = plt.subplots(nrow, ncol, figsize=(2.6 * ncol, 2.6 * nrow + 0.4), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    _profile_projections(carved, axes[-1])
    for v, ax in enumerate(axes[:-1].flat):
        if v >= nview:
            continue
        ax.imshow(radiance[v], cmap="gray", vmin=0.0, vmax=vmax)
        for name, colour in (("cloud_mask", "cyan"), ("hull_silhouette", "red")):
            field = carved[name].values[v]
            if field.any() and not field.all():
                ax.contour(field, levels=[0.5], colors=colour, linewidths=0.8)
        ax.set_title(f"view {v}", fontsize=8)
    fig.suptitle(
        f"space carving: cloudy pixels (cyan), hull silhouette (red); k = {carved.attrs['k']} "
        f"of {nview} views, {int(carved['hull'].sum())} voxels; "
        f"{carved.attrs['profile']} profile (bottom row)",
        fontsize=9,
    )
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _profile_projections(carved: xr.Dataset, axes) -> None:
    """The extinction profile summed along z, y and x on the first three of ``axes``."""
    profile = carved["extinction_profile"].transpose("x", "y", "z")
    edges = {
        name: (float(profile[name][0]), float(profile[name][-1])) for name in ("x", "y", "z")
    }
    for ax, (along, across, up) in zip(axes, (("z", "x", "y"), ("y", "x", "z"),
                                               ("x", "y", "z")), strict=False):
        image = profile.sum(along).transpose(up, across).values
        ax.axis("on")
        ax.imshow(image, origin="lower", cmap="magma", aspect="auto",
                  extent=(*edges[across], *edges[up]))
        ax.set_xlabel(f"{across} [km]", fontsize=7)
        ax.set_ylabel(f"{up} [km]", fontsize=7)
        ax.tick_params(labelsize=6)
        ax.set_title(f"profile summed along {along}", fontsize=8)
