"""Which pixels see cloud: each pixel's clear-sky background and the cloudy-pixel rule of
space carving (:mod:`cloudct.retrieval.carving`, steps 1 and 2), with the cameras'
projection (pinhole or orthographic), the pixel rays and the periodic copies of the box
that they share with the carving's votes."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import xarray as xr

from cloudct.mc.cameras import ORTHOGRAPHIC, PINHOLE, CameraArrays, camera_arrays
from cloudct.mc.scene import Scene, check_scene, periodic_copy_ranges
from cloudct.medium import (
    cell_edges,
    validate_medium,
)

#: Default cloudy-pixel rule (see :func:`cloud_masks`).
SIGNAL_FRACTION = 0.02
SIGNAL_PERCENTILE = 99.0
NOISE_MULTIPLE = 3.0
#: Sub-pixel rays per axis of the clear-sky background.
BACKGROUND_SUBPIXELS = 4


# ---------------------------------------------------------------------------------------
# Geometry: projection and rays
# ---------------------------------------------------------------------------------------


def project_points(
    cams: CameraArrays, view: int, points: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (row, col) of camera ``view`` seeing ``points`` (..., 3) [km]; -1 where a
    point is behind the camera (its image plane) or outside the image. The vectorised twin
    of :func:`cloudct.mc.cameras.project` (the same pinhole and orthographic models and
    pixel edges)."""
    d = points - cams.position[view]
    depth = d @ cams.forward[view]
    u = d @ cams.right[view]
    v = d @ cams.up[view]
    if cams.projection[view] == PINHOLE:
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = u / depth, v / depth
    hw, hh = cams.half_width[view], cams.half_height[view]
    inside = (depth > 0.0) & (-hw <= u) & (u < hw) & (-hh < v) & (v <= hh)
    col = np.minimum(np.floor((u + hw) / (2.0 * hw) * cams.ncols), cams.ncols - 1)
    row = np.minimum(np.floor((hh - v) / (2.0 * hh) * cams.nrows), cams.nrows - 1)
    return np.where(inside, row, -1).astype(np.int64), np.where(inside, col, -1).astype(np.int64)


def _subpixel_centres(
    cams: CameraArrays, view: int, subpixels: int
) -> tuple[np.ndarray, np.ndarray]:
    """Image-plane coordinates (u, v) along ``right`` and ``up`` (pinhole: on the plane at
    unit distance; orthographic: on the image rectangle, km) of the centres of the
    ``subpixels`` x ``subpixels`` sub-pixels of every pixel, each (nrows, ncols,
    subpixels^2, 1); sub-pixel a * subpixels + b lies in sub-row a and sub-column b."""
    hw, hh = cams.half_width[view], cams.half_height[view]
    s = subpixels
    offsets = (np.arange(s) + 0.5) / s
    u = -hw + (np.arange(cams.ncols)[:, None] + offsets) * (2.0 * hw / cams.ncols)
    v = hh - (np.arange(cams.nrows)[:, None] + offsets) * (2.0 * hh / cams.nrows)
    shape = (cams.nrows, cams.ncols, s, s)
    u = np.broadcast_to(u[None, :, None, :], shape).reshape(cams.nrows, cams.ncols, s * s, 1)
    v = np.broadcast_to(v[:, None, :, None], shape).reshape(cams.nrows, cams.ncols, s * s, 1)
    return u, v


def pixel_rays(cams: CameraArrays, view: int, subpixels: int = 1) -> np.ndarray:
    """Unit directions of the rays of ``view`` through the centres of the ``subpixels`` x
    ``subpixels`` sub-pixels of every pixel, (nrows, ncols, subpixels^2, 3): from the
    pinhole, or the view direction of an orthographic camera (the rays of
    :func:`cloudct.mc.cameras.pixel_ray`; they start at :func:`pixel_ray_origins`)."""
    u, v = _subpixel_centres(cams, view, subpixels)
    if cams.projection[view] == ORTHOGRAPHIC:
        return np.broadcast_to(cams.forward[view], (*u.shape[:-1], 3)).copy()
    rays = cams.forward[view] + u * cams.right[view] + v * cams.up[view]
    return rays / np.linalg.norm(rays, axis=-1, keepdims=True)


def pixel_ray_origins(cams: CameraArrays, view: int, subpixels: int = 1) -> np.ndarray:
    """Where the rays of :func:`pixel_rays` start, (nrows, ncols, subpixels^2, 3) [km]: the
    pinhole, or the sub-pixel centres on an orthographic camera's image rectangle."""
    u, v = _subpixel_centres(cams, view, subpixels)
    if cams.projection[view] == ORTHOGRAPHIC:
        return cams.position[view] + u * cams.right[view] + v * cams.up[view]
    return np.broadcast_to(cams.position[view], (*u.shape[:-1], 3)).copy()


def ray_box(
    origin: np.ndarray, rays: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Distances (t_in, t_out) along ``rays`` (..., 3) from ``origin`` (one point, or one
    per ray) through the box [lo, hi] (slab method; infinite bounds allowed). t_in >= t_out
    where a ray misses."""
    # a ray parallel to a pair of faces gets +-inf there (inside the slab for every t, or
    # never), or NaN (0/0) when it runs in a face plane: counted as inside
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (lo - origin) / rays
        t1 = (hi - origin) / rays
    near = np.where(np.isnan(t0), -np.inf, np.minimum(t0, t1))
    far = np.where(np.isnan(t1), np.inf, np.maximum(t0, t1))
    return np.maximum(near.max(axis=-1), 0.0), far.min(axis=-1)


def ray_steps(
    t_in: np.ndarray, t_out: np.ndarray, step: float
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Steps along rays from t_in to t_out: yields (live, midpoint t, segment length), the
    last segment of each ray cut at t_out."""
    start = t_in.copy()
    while np.any(live := start < t_out):
        end = np.minimum(start[live] + step, t_out[live])
        yield live, 0.5 * (start[live] + end), end - start[live]
        start[live] = end


def cell_index(edges: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Index of the cell of ``edges`` holding each value (clamped to the grid)."""
    return np.clip(np.searchsorted(edges, values, side="right") - 1, 0, len(edges) - 2)


def box_corners(edges: tuple[np.ndarray, ...]) -> tuple[np.ndarray, np.ndarray]:
    """The lowest and the highest corner of the box of the cell ``edges`` [km]."""
    return np.array([e[0] for e in edges]), np.array([e[-1] for e in edges])


def medium_bounds(scene: Scene, edges: tuple[np.ndarray, ...]) -> tuple[np.ndarray, np.ndarray]:
    """The corners of what the cameras look into: the box, or with periodic boundaries the
    whole slab (x and y unbounded)."""
    lo, hi = box_corners(edges)
    if scene.periodic:
        lo[:2], hi[:2] = -np.inf, np.inf
    return lo, hi


def wrapped_index(edges: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Index of the cell of ``edges`` holding each value, the axis being periodic with the
    grid's length (the horizontal axes under periodic boundaries)."""
    return cell_index(edges, edges[0] + np.mod(values - edges[0], edges[-1] - edges[0]))


def view_copies(scene: Scene, edges: tuple[np.ndarray, ...]) -> list[np.ndarray]:
    """Per view, the horizontal shifts (i Lx, j Ly, 0) [km] of the periodic copies of the
    box that the view can see (:func:`cloudct.mc.scene.periodic_copy_ranges`),
    float64[ncopy, 3]; the box itself, (0, 0, 0), with open boundaries."""
    lengths = [e[-1] - e[0] for e in edges[:2]]
    shifts = []
    for i0, i1, j0, j1 in periodic_copy_ranges(scene, tuple(edges)):
        i, j = np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1 + 1), indexing="ij")
        shifts.append(np.stack([i.ravel() * lengths[0], j.ravel() * lengths[1],
                                np.zeros(i.size)], axis=1))
    return shifts


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

    lo, hi = medium_bounds(scene, edges)
    step = 0.5 * float(np.diff(z_edges).min())
    cams = camera_arrays(scene.cameras)
    out = np.zeros((len(scene.cameras), cams.nrows, cams.ncols))
    for v in range(out.shape[0]):
        origins = pixel_ray_origins(cams, v, subpixels)
        rays = pixel_rays(cams, v, subpixels)
        t_in, t_out = ray_box(origins, rays, lo, hi)
        mu = -(rays @ sun)  # cos(scattering angle): sun's rays vs. direction to the camera
        phase = 3.0 / (16.0 * np.pi) * (1.0 + mu * mu)
        radiance = np.zeros(t_in.shape)
        tau_view = np.zeros(t_in.shape)
        for live, t, length in ray_steps(t_in, t_out, step):
            z = origins[live][:, 2] + t * rays[live][:, 2]
            b = beta[cell_index(z_edges, z)]
            radiance[live] += (
                b * length * np.exp(-(tau_view[live] + 0.5 * b * length)) * sun_transmittance(z)
            )
            tau_view[live] += b * length
        radiance *= albedo * phase
        if scene.ground_albedo is not None:
            ground = (t_in < t_out) & (
                np.abs(origins[..., 2] + t_out * rays[..., 2] - z_edges[0])
                <= 1e-9 + 1e-9 * t_out
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
    lo, hi = medium_bounds(scene, cell_edges(template))
    cams = camera_arrays(scene.cameras)
    signal = np.zeros(radiance.shape[0])
    mask = np.zeros(radiance.shape, dtype=bool)
    for v in range(radiance.shape[0]):
        if threshold is None:
            t_in, t_out = ray_box(pixel_ray_origins(cams, v)[:, :, 0],
                                  pixel_rays(cams, v)[:, :, 0], lo, hi)
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
