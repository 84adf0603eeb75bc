"""Space carving: the cloud's hull from its multi-view images, and the initial medium.

Seed paper Sec. 6.1.1: the retrieval starts from the space-carved hull of the cloud
[Kutulakos and Seitz 2000] filled with the cloud's mean extinction. Here:

1. **Cloudy pixels.** In each view v a pixel is cloudy when its radiance exceeds the view's
   clear-sky background b_v by more than the threshold t_v (:func:`cloud_masks`).
2. **Votes.** A voxel is projected onto each view by the cameras' pinhole model
   (:func:`cloudct.mc.cameras.project`) at the centres of its ``subsamples``^3 sub-cells.
   View v votes for the voxel when one of those points falls on a cloudy pixel, or when one
   falls outside the image or on a masked (NaN) pixel: a view cannot carve away what it
   does not see.
3. **Hull.** The voxels with at least k votes (default: every view) form the hull.

:func:`initial_medium` fills the hull with one cloud extinction (by default the estimate
stored by :func:`carve`, see :func:`extinction_estimate`) and clears the rest.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
import xarray as xr
from numba import njit, prange

from cloudct.mc.cameras import CameraArrays, camera_arrays, pixel_ray, project
from cloudct.mc.scene import Scene, check_scene
from cloudct.medium import (
    DEFAULT_CLOUD_ALBEDO,
    DEFAULT_CLOUD_G,
    cell_edges,
    is_optical,
    load_medium,
    optical_medium,
    save_medium,
    validate_medium,
)

#: Default threshold rule (see :func:`cloud_masks`).
BACKGROUND_PERCENTILE = 20.0
PEAK_PERCENTILE = 99.0
RANGE_FRACTION = 0.05
NOISE_MULTIPLE = 3.0
#: Default number of sub-cells per axis at whose centres a voxel is projected.
SUBSAMPLES = 3
#: Relative tolerance (of the box size) for the measurement box matching the template's.
BOX_RTOL = 1e-6


def cloud_masks(
    measurements: xr.Dataset,
    box_edges: tuple[np.ndarray, np.ndarray, np.ndarray],
    threshold: float | None = None,
) -> xr.Dataset:
    """Cloudy pixels of every view, with each view's background and threshold.

    The background b_v of view v is the ``BACKGROUND_PERCENTILE`` (20th) percentile of the
    radiance over the view's pixels whose centre ray crosses the box (clear air seen through
    the box; pixels that miss the box see nothing and are left out). A pixel is cloudy when

        L - b_v > t_v,   t_v = max(RANGE_FRACTION * (L_peak,v - b_v), NOISE_MULTIPLE * sigma)

    with L_peak,v the ``PEAK_PERCENTILE`` (99th) percentile over the same pixels, sigma the
    pixel's ``radiance_noise_std`` (else ``radiance_std_error``, else 0), and the defaults
    RANGE_FRACTION = 0.05 and NOISE_MULTIPLE = 3. A given ``threshold`` replaces t_v in every
    view (radiance units above the background). NaN pixels are never cloudy.

    Returns:
        A Dataset with ``cloud_mask`` (view, row, col) int8 (1 cloudy), ``box_pixels``
        (view, row, col) int8 (1 where the pixel's centre ray crosses the box),
        ``background`` (view) and ``threshold`` (view).
    """
    radiance = measurements["radiance"].values
    sigma = np.zeros_like(radiance)
    for name in ("radiance_noise_std", "radiance_std_error"):
        if name in measurements:
            sigma = measurements[name].values
            break
    cams = camera_arrays(Scene.from_dataset(measurements).cameras)
    lo = np.array([e[0] for e in box_edges])
    hi = np.array([e[-1] for e in box_edges])
    in_box = _box_pixels(cams, lo, hi)
    nview = radiance.shape[0]
    background = np.zeros(nview)
    thresholds = np.zeros(nview)
    mask = np.zeros(radiance.shape, dtype=bool)
    for v in range(nview):
        seen = radiance[v][in_box[v] & np.isfinite(radiance[v])]
        if seen.size == 0:
            raise ValueError(f"view {v} has no measured pixel looking at the box")
        background[v] = np.percentile(seen, BACKGROUND_PERCENTILE)
        if threshold is None:
            peak = np.percentile(seen, PEAK_PERCENTILE)
            range_threshold = RANGE_FRACTION * max(peak - background[v], 0.0)
            pixel_threshold = np.maximum(range_threshold, NOISE_MULTIPLE * sigma[v])
            thresholds[v] = range_threshold
        else:
            pixel_threshold = np.full(radiance.shape[1:], float(threshold))
            thresholds[v] = float(threshold)
        with np.errstate(invalid="ignore"):
            mask[v] = radiance[v] - background[v] > pixel_threshold
    dims = ("view", "row", "col")
    return xr.Dataset(
        {
            "cloud_mask": (dims, mask.astype(np.int8), {
                "units": "1", "long_name": "pixel judged cloudy (1) or clear (0)"}),
            "box_pixels": (dims, in_box.astype(np.int8), {
                "units": "1", "long_name": "pixel whose centre ray crosses the medium's box"}),
            "background": ("view", background, {
                "units": "1", "long_name": "clear-sky background radiance of the view"}),
            "threshold": ("view", thresholds, {
                "units": "1",
                "long_name": "radiance above the background for a cloudy pixel",
                "comment": "pixels also need 3 times their noise standard deviation"
                if threshold is None else "given threshold"}),
        },
        coords={"view": measurements["view"].values},
    )


def carve(
    measurements: xr.Dataset,
    grid_template: xr.Dataset,
    *,
    k: int | None = None,
    threshold: float | None = None,
    subsamples: int = SUBSAMPLES,
    cloud_g: float = DEFAULT_CLOUD_G,
) -> xr.Dataset:
    """The space-carved hull of the cloud on the grid of ``grid_template``.

    Args:
        measurements: a measurement set (images with cameras and sun, see
            :mod:`data_synth.measurements`).
        grid_template: a medium whose grid (x, y, z and z_bounds) the hull is built on.
            When the measurements record the box of the medium they were made of
            (``medium_box``), the template's box must be the same (its resolution may
            differ).
        k: the number of views that must see a voxel as cloudy (1 <= k <= views);
            default every view.
        threshold: cloudy-pixel threshold [radiance above the background]; default the
            per-view rule of :func:`cloud_masks`.
        subsamples: sub-cells per axis at whose centres each voxel is projected.
        cloud_g: the cloud's HG asymmetry parameter, for :func:`extinction_estimate`.

    Returns:
        A Dataset on the template's grid with ``hull`` (x, y, z) int8 (1 inside),
        ``votes`` (x, y, z) (views that see the voxel as cloudy or cannot see it), the
        variables of :func:`cloud_masks`, ``hull_silhouette`` (view, row, col) int8 (pixels
        whose centre ray crosses the hull) and the attributes ``k``, ``subsamples`` and
        ``extinction_estimate`` [km-1].

    Raises:
        ValueError: a camera inside the box or not seeing it, a template box different
            from the measured medium's, a bad k or subsamples.
    """
    from data_synth.measurements import validate_measurements

    validate_measurements(measurements)
    edges = cell_edges(grid_template)
    _check_box(measurements, edges)
    scene = Scene.from_dataset(measurements)
    check_scene(scene, edges)
    nview = len(scene.cameras)
    k = nview if k is None else int(k)
    if not 1 <= k <= nview:
        raise ValueError(f"k must be between 1 and the number of views ({nview}), got {k}")
    if int(subsamples) < 1:
        raise ValueError(f"subsamples must be >= 1, got {subsamples}")

    masks = cloud_masks(measurements, edges, threshold)
    cams = camera_arrays(scene.cameras)
    radiance = measurements["radiance"].values
    votes, points_in_view = _votes(
        cams, masks["cloud_mask"].values.astype(np.bool_), np.isfinite(radiance),
        *edges, int(subsamples),
    )
    blind = np.flatnonzero(points_in_view == 0)
    if blind.size:
        raise ValueError(f"camera {int(blind[0])} does not see the template grid's box")
    hull = votes >= k
    silhouette = _silhouette(cams, hull, *edges)

    ds = masks.copy()
    coords = {name: grid_template[name] for name in ("x", "y", "z")}
    ds = ds.assign_coords(coords)
    if "z_bounds" in grid_template:
        ds["z_bounds"] = grid_template["z_bounds"]
    grid = ("x", "y", "z")
    ds["hull"] = (grid, hull.astype(np.int8), {
        "units": "1", "long_name": "space-carved cloud hull (1 inside)"})
    ds["votes"] = (grid, votes, {
        "units": "1", "long_name": "views seeing the voxel as cloudy or not seeing it"})
    ds["hull_silhouette"] = (("view", "row", "col"), silhouette.astype(np.int8), {
        "units": "1", "long_name": "pixel whose centre ray crosses the hull"})
    ds.attrs.update(
        title="cloudct space-carved hull",
        Conventions="CF-1.8",
        k=k,
        views=nview,
        subsamples=int(subsamples),
        threshold_rule="given" if threshold is None else f"{threshold:g} above background",
        extinction_estimate=extinction_estimate(measurements, ds, cloud_g=cloud_g),
        extinction_estimate_units="km-1",
    )
    if threshold is None:
        ds.attrs["threshold_rule"] = (
            f"per view: max({RANGE_FRACTION:g} * (p{PEAK_PERCENTILE:g} - background), "
            f"{NOISE_MULTIPLE:g} * pixel noise std) above the p{BACKGROUND_PERCENTILE:g} "
            "background of the pixels seeing the box"
        )
    return ds


def extinction_estimate(
    measurements: xr.Dataset, carved: xr.Dataset, *, cloud_g: float = DEFAULT_CLOUD_G
) -> float:
    """A mean cloud extinction [km-1] for the hull, from the images by two-stream theory.

    The mean radiance of the cloudy pixels above their view's background, over all views,
    is read as the reflectance of a plane-parallel, non-absorbing cloud seen under a sun
    of zenith angle theta0: R = pi L / cos(theta0). The two-stream relation
    R = (1 - g) tau / (2 + (1 - g) tau) (e.g. Bohren and Clothiaux 2006, Ch. 6) gives the
    optical thickness tau = 2 R / ((1 - g)(1 - R)), and the extinction is tau over the
    hull's mean geometric thickness (hull voxels' heights summed per column, averaged over
    the hull's columns). Finite clouds leak light through their sides and look darker
    than slabs, so the estimate is on the low side: a starting value, not a retrieval.
    """
    radiance = measurements["radiance"].values
    cloudy = carved["cloud_mask"].values.astype(bool)
    if not cloudy.any() or not carved["hull"].values.any():
        return 0.0
    excess = radiance - carved["background"].values[:, None, None]
    mean_excess = float(np.nanmean(excess[cloudy]))
    mu0 = math.cos(math.radians(float(measurements.attrs["sun_zenith"])))
    reflectance = min(math.pi * max(mean_excess, 0.0) / mu0, 0.99)
    tau = 2.0 * reflectance / ((1.0 - cloud_g) * (1.0 - reflectance))
    z_edges = cell_edges(carved)[2]
    thickness = (carved["hull"].values * np.diff(z_edges)).sum(axis=2)
    return float(tau / thickness[thickness > 0].mean())


def initial_medium(
    carved: xr.Dataset | xr.DataArray,
    template_medium: xr.Dataset,
    extinction: float | None = None,
) -> xr.Dataset:
    """The retrieval's initial medium: constant cloud extinction in the hull, zero outside.

    Args:
        carved: the result of :func:`carve`, or a hull mask (x, y, z) on the template's
            grid (then ``extinction`` is required).
        template_medium: gives the grid and the air (kept as they are) and, when it is
            optical, the cloud albedo and phase function (HG g or tabulated); a
            microphysical template gives the defaults (albedo 0.99, HG g = 0.85).
        extinction: the cloud extinction in the hull [km-1]; default the
            ``extinction_estimate`` of ``carved``.

    Returns:
        A validated optical medium.

    Raises:
        ValueError: grids that differ, an empty hull, or a missing or negative extinction.
    """
    validate_medium(template_medium)
    mask = carved["hull"] if isinstance(carved, xr.Dataset) else carved
    if extinction is None:
        if "extinction_estimate" not in carved.attrs:
            raise ValueError("give the extinction: the hull carries no extinction_estimate")
        extinction = float(carved.attrs["extinction_estimate"])
    if not (math.isfinite(extinction) and extinction >= 0.0):
        raise ValueError(f"extinction must be finite and >= 0, got {extinction}")
    for name in ("x", "y", "z"):
        if name not in mask.coords or not np.allclose(
            mask[name].values, template_medium[name].values, rtol=0.0, atol=1e-9
        ) or mask.sizes[name] != template_medium.sizes[name]:
            raise ValueError(f"the hull's grid differs from the template's along {name}")
    hull = mask.transpose("x", "y", "z").values.astype(bool)
    if not hull.any():
        raise ValueError("the hull is empty: nothing to fill (lower the threshold or k)")

    cloud: dict = {"cloud_albedo": DEFAULT_CLOUD_ALBEDO, "cloud_g": DEFAULT_CLOUD_G}
    if is_optical(template_medium):
        cloud = {"cloud_albedo": template_medium["cloud_albedo"]}
        if "cloud_g" in template_medium:
            cloud["cloud_g"] = template_medium["cloud_g"]
        else:
            table = template_medium["cloud_phase"]
            cloud["cloud_phase"] = (table.values, table["scattering_angle"].values)
            cloud["cloud_phase_index"] = template_medium["cloud_phase_index"]
    return optical_medium(
        template_medium["x"].values,
        template_medium["y"].values,
        template_medium["z"].values,
        np.where(hull, extinction, 0.0),
        air_extinction=template_medium["air_extinction"],
        air_albedo=float(template_medium["air_albedo"]),
        z_bounds=template_medium["z_bounds"].values if "z_bounds" in template_medium else None,
        wavelength=template_medium.attrs.get("wavelength"),
        title="cloudct initial medium (space-carved hull)",
        source=f"cloudct.retrieval.carving.initial_medium, extinction {extinction:g} km-1",
        **cloud,
    )


def _check_box(measurements: xr.Dataset, edges: tuple[np.ndarray, ...]) -> None:
    """The template's box must be the one the measurements were made of (when recorded)."""
    if "medium_box" not in measurements.attrs:
        return
    measured = np.asarray(measurements.attrs["medium_box"], dtype=float).ravel()
    template = np.array([v for e in edges for v in (e[0], e[-1])])
    size = max(float(np.max(template[1::2] - template[::2])), 1e-12)
    if measured.shape != (6,) or not np.allclose(measured, template, rtol=0, atol=BOX_RTOL * size):
        raise ValueError(
            "the template grid's box (x, y, z ranges "
            f"{_ranges(template)} km) differs from the box the measurements were made of "
            f"({_ranges(measured)} km)"
        )


def _ranges(box: np.ndarray) -> str:
    return ", ".join(f"{box[i]:.4g}..{box[i + 1]:.4g}" for i in range(0, len(box), 2))


def _box_pixels(cams: CameraArrays, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """bool[view, row, col]: the pixel's centre ray crosses the box [lo, hi]."""
    nview = cams.position.shape[0]
    out = np.zeros((nview, cams.nrows, cams.ncols), dtype=np.bool_)
    _box_pixels_kernel(cams, lo, hi, out)
    return out


@njit(cache=True)
def _ray_box(ox, oy, oz, dx, dy, dz, lo, hi):
    """Entry and exit distances of the ray o + t d through the box (t_in > t_out: missed)."""
    t_in, t_out = 0.0, np.inf
    for o, d, a, b in ((ox, dx, lo[0], hi[0]), (oy, dy, lo[1], hi[1]), (oz, dz, lo[2], hi[2])):
        if d == 0.0:
            if o < a or o > b:
                return 1.0, 0.0
        else:
            t0 = (a - o) / d
            t1 = (b - o) / d
            t_in = max(t_in, min(t0, t1))
            t_out = min(t_out, max(t0, t1))
    return t_in, t_out


@njit(cache=True)
def _box_pixels_kernel(cams, lo, hi, out):
    for v in range(out.shape[0]):
        p = cams.position[v]
        for row in range(cams.nrows):
            for col in range(cams.ncols):
                dx, dy, dz = pixel_ray(cams, v, row, col, 0.5, 0.5)
                t_in, t_out = _ray_box(p[0], p[1], p[2], dx, dy, dz, lo, hi)
                out[v, row, col] = t_in < t_out


@njit(cache=True)
def _votes(cams, cloudy, observed, x_edges, y_edges, z_edges, nsub):
    """Votes per voxel, int16[nx, ny, nz], and the number of sub-cell centres that land in
    each view's image, int64[nview] (see the module docstring for the rule)."""
    nx, ny, nz = len(x_edges) - 1, len(y_edges) - 1, len(z_edges) - 1
    nview = cams.position.shape[0]
    votes = np.zeros((nx, ny, nz), dtype=np.int16)
    landed = np.zeros((nx, nview), dtype=np.int64)
    for i in range(nx):
        for j in range(ny):
            for kz in range(nz):
                for v in range(nview):
                    vote = False
                    for a in range(nsub):
                        px = x_edges[i] + (a + 0.5) / nsub * (x_edges[i + 1] - x_edges[i])
                        for b in range(nsub):
                            py = y_edges[j] + (b + 0.5) / nsub * (y_edges[j + 1] - y_edges[j])
                            for c in range(nsub):
                                pz = z_edges[kz] + (c + 0.5) / nsub * (
                                    z_edges[kz + 1] - z_edges[kz])
                                row, col, _, _, _, _ = project(cams, v, px, py, pz)
                                if row < 0:
                                    vote = True
                                    continue
                                landed[i, v] += 1
                                if cloudy[v, row, col] or not observed[v, row, col]:
                                    vote = True
                    if vote:
                        votes[i, j, kz] += 1
    return votes, landed.sum(axis=0)


@njit(cache=True)
def _voxel_index(edges, t):
    """Index of the cell of ``edges`` containing t (clamped to the grid)."""
    return min(max(np.searchsorted(edges, t, side="right") - 1, 0), len(edges) - 2)


@njit(cache=True)
def _silhouette(cams, hull, x_edges, y_edges, z_edges):
    """bool[view, row, col]: the pixel's centre ray crosses a hull voxel (ray marched at
    steps of a quarter of the smallest cell size)."""
    nview = cams.position.shape[0]
    out = np.zeros((nview, cams.nrows, cams.ncols), dtype=np.bool_)
    lo = np.array([x_edges[0], y_edges[0], z_edges[0]])
    hi = np.array([x_edges[-1], y_edges[-1], z_edges[-1]])
    step = 0.25 * min(np.diff(x_edges).min(), np.diff(y_edges).min(), np.diff(z_edges).min())
    for v in range(nview):
        p = cams.position[v]
        for row in range(cams.nrows):
            for col in range(cams.ncols):
                dx, dy, dz = pixel_ray(cams, v, row, col, 0.5, 0.5)
                t_in, t_out = _ray_box(p[0], p[1], p[2], dx, dy, dz, lo, hi)
                t = t_in + 0.5 * step
                while t < t_out:
                    i = _voxel_index(x_edges, p[0] + t * dx)
                    j = _voxel_index(y_edges, p[1] + t * dy)
                    kz = _voxel_index(z_edges, p[2] + t * dz)
                    if hull[i, j, kz]:
                        out[v, row, col] = True
                        break
                    t += step
    return out


def save_hull_figure(carved: xr.Dataset, measurements: xr.Dataset, path: str | Path) -> Path:
    """A figure of every view: the measured image with the outline of its cloudy pixels
    (cyan) and of the hull's silhouette (red). Returns the path written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    radiance = measurements["radiance"].values
    nview = radiance.shape[0]
    ncol = math.ceil(math.sqrt(nview))
    nrow = math.ceil(nview / ncol)
    vmax = float(np.nanmax(radiance)) or 1.0
    fig, axes = plt.subplots(nrow, ncol, figsize=(2.6 * ncol, 2.6 * nrow + 0.4), squeeze=False)
    for v, ax in enumerate(axes.flat):
        ax.axis("off")
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
        f"of {nview}, {int(carved['hull'].sum())} voxels, "
        f"extinction estimate {carved.attrs['extinction_estimate']:.3g} /km",
        fontsize=9,
    )
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def _cli_carve(args: argparse.Namespace) -> int:
    """``cloudct carve``: hull and initial medium from measurements."""
    from cloudct.mc.render import single_cloud_medium
    from data_synth.measurements import load_measurements

    measurements = load_measurements(args.measurements)
    template = single_cloud_medium() if args.medium is None else load_medium(args.medium)
    output = Path(args.output)
    if output.exists() and not args.overwrite:
        raise FileExistsError(f"{output} exists (use --overwrite)")
    carved = carve(measurements, template, k=args.k, threshold=args.threshold)
    medium = initial_medium(carved, template, extinction=args.extinction)
    save_medium(medium, output, overwrite=args.overwrite)
    text = ""
    if args.figure:
        text = f" and {save_hull_figure(carved, measurements, args.figure)}"
    extinction = float(medium["cloud_extinction"].max())
    print(
        f"wrote {output}{text}: hull of {int(carved['hull'].sum())} of "
        f"{carved['hull'].size} voxels (k = {carved.attrs['k']} of {carved.attrs['views']} "
        f"views), cloud extinction {extinction:.3g} /km"
    )
    return 0


def register_cli(subparsers: argparse._SubParsersAction) -> None:
    """Add ``cloudct carve``."""
    p = subparsers.add_parser(
        "carve",
        help="space-carve the cloud's hull from measurements into an initial medium",
        description="Space carving (seed paper Sec. 6.1.1): voxels seen as cloudy by at "
        "least K views form the hull, filled with a constant extinction (default: a "
        "two-stream estimate from the images) on the grid of a template medium.",
    )
    p.add_argument("measurements", help="measurement netCDF (from `cloudct synth`)")
    p.add_argument("-o", "--output", default="init.nc", help="output medium netCDF")
    p.add_argument("--medium", help="template medium netCDF giving the grid and air "
                   "(default: the bundled single cloud)")
    p.add_argument("--k", type=int, help="views that must see a voxel as cloudy (default all)")
    p.add_argument("--threshold", type=float,
                   help="cloudy-pixel radiance above the background (default per view)")
    p.add_argument("--extinction", type=float, help="cloud extinction in the hull [1/km]")
    p.add_argument("--figure", help="PNG of the views with the hull's silhouette")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(func=_cli_carve)
