"""The measurement format (what a retrieval reads), and synthetic measurements.

A *measurement set* holds multi-view images with their cameras and the sun; its schema,
for users who bring their own images, is docs/measurements.md. :func:`validate_measurements`
checks it, :func:`save_measurements` and :func:`load_measurements` write and read it.

:func:`synthesize_measurements` renders a medium with many photons
(:func:`cloudct.mc.render.render`: the forward estimator, or the combined one, which keeps
Mie optics' diffraction peak free of fireflies) and optionally adds camera noise
(:class:`NoiseModel`). The result, a *measurement set*, is the render's images Dataset
(``radiance`` over (view, row, col), the cameras as variables over ``view``, the sun and
boundaries as attributes) with, in addition:

* ``radiance_noise_std`` (view, row, col): the expected standard deviation of each measured
  pixel about the true radiance: the noise model's and the render's Monte Carlo error added
  in quadrature. Its inverse square is the natural loss weight.
* attributes ``wavelength`` [micron], the noise parameters (``noise_model``,
  ``noise_electrons``, ``noise_reference_radiance``, ``noise_read_electrons``,
  ``noise_seed``), the render's ``photons`` and ``seed``, and the box and shape of the
  medium's grid (``medium_box`` = x_min, x_max, y_min, y_max, z_min, z_max [km];
  ``medium_shape`` = nx, ny, nz) so that a retrieval grid can be checked against them.
* for a medium with a non-exponential transmittance (docs/transmittance.md), its family
  (attribute ``transmittance``) and mode (variable ``transmittance_mode``: a scalar, or over
  the medium's x, y, z with their coordinates), which ``cloudct retrieve --transmittance
  medium`` retrieves under (:func:`measured_transmittance`).

Noise model (photon-transfer form, as for a CCD/CMOS sensor): a pixel of radiance L
collects on average N = gain * L photo-electrons, with gain = ``electrons`` /
``reference_radiance`` (``electrons`` is the mean count at the reference radiance; by
default 1/pi, the radiance of a white Lambertian plate facing the sun). The count is
Poisson distributed; read-out adds Gaussian noise of ``read_noise`` electrons rms; the
measured radiance is the total divided by the gain:

    L_measured = (Poisson(gain * L) + Normal(0, read_noise^2)) / gain,
    E[L_measured] = L,     Var[L_measured] = L / gain + (read_noise / gain)^2.

Measured radiances are not clipped at zero (clipping would bias dark pixels), so read
noise can give slightly negative values, as a dark-subtracted camera does.

A measurement set may hold several bands (:mod:`cloudct.measurement_bands`, which
stacks and synthesizes them): :func:`validate_measurements` checks them,
:func:`band_measurements` takes one out; readers of one band refuse several.
"""

from __future__ import annotations

import math
import os
import warnings
from dataclasses import dataclass, replace
from functools import partial

import numpy as np
import xarray as xr

from cloudct.mc.cameras import cameras_from_dataset
from cloudct.mc.render import RADIANCE_UNITS, default_method, render
from cloudct.mc.scene import Scene, single_cloud_scene_of
from cloudct.medium import (
    MediumError,
    cell_edges,
    check_transmittance,
    transmittance_model,
    validate_medium,
    with_transmittance,
)
from cloudct.netcdf import load_netcdf, save_netcdf
from cloudct.optics import to_optical
from cloudct.physics.mie import DEFAULT_WAVELENGTH
from cloudct.units import units_problem

#: Default number of photons of a synthetic measurement (forward estimator).
DEFAULT_PHOTONS = 10_000_000
#: Batches of a synthetic measurement's render (for its standard errors).
DEFAULT_BATCHES = 32
#: Default reference radiance of the noise model: a white Lambertian plate facing the sun.
WHITE_PLATE_RADIANCE = 1.0 / math.pi

IMAGE_DIMS = ("view", "row", "col")
SCENE_ATTRS = ("sun_zenith", "sun_azimuth", "boundary")
#: The units of the variables that carry them (docs/measurements.md).
_UNITS = {"radiance": "1", "radiance_noise_std": "1", "radiance_std_error": "1",
          "position": "km", "lookat": "km", "fov": "degree"}


#: The dimension of the bands of a multi-spectral measurement set; its coordinate is
#: ``wavelength`` [micron].
BAND = "band"
_BAND_IMAGE_DIMS = (BAND, *IMAGE_DIMS)
#: How near [micron] a band's wavelength must be to the one asked of :func:`band_measurements`.
BAND_TOLERANCE = 0.01
#: The camera variables (:func:`cloudct.mc.cameras.cameras_dataset`): one set for all bands.
CAMERA_VARIABLES = ("position", "lookat", "up", "fov", "nrows", "ncols", "projection", "width")


class MeasurementError(ValueError):
    """A measurement Dataset or file that does not follow the measurement schema."""


@dataclass(frozen=True)
class NoiseModel:
    """Photon (shot) noise and Gaussian read noise of a camera, counted in electrons.

    Attributes:
        electrons: mean number of photo-electrons a pixel collects at ``reference_radiance``
            (> 0); sets the gain = electrons / reference_radiance [electrons per unit
            radiance]. The signal-to-noise ratio of a pixel at the reference radiance is
            sqrt(electrons) without read noise.
        read_noise: read-out noise [electrons rms], >= 0.
        reference_radiance: the radiance at which a pixel collects ``electrons`` on average
            (default 1/pi, a white Lambertian plate facing the sun).
    """

    electrons: float
    read_noise: float = 0.0
    reference_radiance: float = WHITE_PLATE_RADIANCE

    def __post_init__(self) -> None:
        if not (math.isfinite(self.electrons) and self.electrons > 0.0):
            raise ValueError(f"noise electrons must be positive, got {self.electrons}")
        if not (math.isfinite(self.read_noise) and self.read_noise >= 0.0):
            raise ValueError(f"read noise must be >= 0 electrons, got {self.read_noise}")
        if not (math.isfinite(self.reference_radiance) and self.reference_radiance > 0.0):
            raise ValueError(
                f"reference radiance must be positive, got {self.reference_radiance}"
            )

    @property
    def gain(self) -> float:
        """Electrons per unit radiance."""
        return self.electrons / self.reference_radiance

    def variance(self, radiance: np.ndarray) -> np.ndarray:
        """Variance of a measured radiance about the true ``radiance`` (>= 0):
        L / gain + (read_noise / gain)^2, in radiance units squared."""
        return np.asarray(radiance) / self.gain + (self.read_noise / self.gain) ** 2

    def apply(self, radiance: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """A noisy measurement of the true ``radiance`` (finite, >= 0), drawn from ``rng``."""
        radiance = np.asarray(radiance, dtype=float)
        if not np.all(np.isfinite(radiance)) or np.any(radiance < 0.0):
            raise ValueError("the noise model needs finite, non-negative radiances")
        electrons = rng.poisson(radiance * self.gain).astype(float)
        electrons += rng.normal(0.0, self.read_noise, size=radiance.shape)
        return electrons / self.gain


def synthesize_measurements(
    medium: xr.Dataset,
    scene: Scene | None = None,
    *,
    photons: int = DEFAULT_PHOTONS,
    seed: int = 0,
    noise: NoiseModel | None = None,
    noise_seed: int | None = None,
    wavelength: float = DEFAULT_WAVELENGTH,
    optics: str | None = None,
    batches: int = DEFAULT_BATCHES,
    progress: bool | None = None,
    backend: str = "cpu",
    method: str | None = None,
) -> xr.Dataset:
    """Synthetic measurements of ``medium``: a render plus optional camera noise.

    Args:
        medium: an optical medium (used as it is), or a microphysical one (converted with
            the Mie tables at ``wavelength``).
        scene: cameras, sun and boundaries; default the seed paper's nine-camera
            single-cloud geometry for the medium's box (:func:`single_cloud_scene`).
        photons: forward photons of the render.
        seed: seed of the render.
        noise: the camera noise model, or None for noise-free images (the render's Monte
            Carlo error is then the only noise).
        noise_seed: seed of the noise draws (numpy's default generator); default ``seed``.
        wavelength: [micron]. An optical medium that records its ``wavelength`` must match.
        optics: the cloud optics of a microphysical medium (:func:`cloudct.optics.to_optical`;
            None: its recorded choice, else the default). The file records the optics used.
        batches: independent batches of the render (for its standard errors).
        progress: show a progress bar (None: only on a terminal).
        backend: where the render runs, ``"cpu"``, ``"cuda"`` or ``"auto"``
            (:mod:`cloudct.mc.backend`); recorded in the attribute ``backend``.
        method: the render's estimator, ``"forward"`` or ``"combined"`` (forward photons
            and 4 backward paths per photon, weighted by multiple importance sampling:
            :mod:`cloudct.mc.combined`); None: combined for a medium with tabulated (Mie)
            phase functions, whose diffraction peak gives the forward images fireflies,
            else forward (:func:`cloudct.mc.render.default_method`). Recorded in the
            attribute ``method``.

    Returns:
        The measurement set described in the module docstring.

    Raises:
        ValueError: a bad medium, scene, photon count or a wavelength mismatch.
    """
    validate_medium(medium)
    if not (math.isfinite(wavelength) and wavelength > 0.0):
        raise ValueError(f"wavelength must be positive, got {wavelength}")
    medium = to_optical(medium, wavelength=wavelength, optics=optics)  # optical: as it is
    if "wavelength" in medium.attrs and not np.isclose(
        float(medium.attrs["wavelength"]), wavelength
    ):
        raise ValueError(
            f"the medium's optics are for {medium.attrs['wavelength']} micron, "
            f"not {wavelength} micron"
        )
    edges = cell_edges(medium)
    if scene is None:
        scene = single_cloud_scene_of(medium)
    if method is None:
        method = default_method(medium)
    if method not in ("forward", "combined"):
        raise ValueError(f"method must be 'forward' or 'combined', got {method!r}")
    images = render(medium, scene, photons=photons, seed=seed, batches=batches,
                    progress=progress, backend=backend, method=method)

    clean = images["radiance"].values
    mc_variance = images["radiance_std_error"].values ** 2
    noise_seed = seed if noise_seed is None else int(noise_seed)
    if noise is None:
        measured, noise_variance = clean, np.zeros_like(clean)
    else:
        measured = noise.apply(clean, np.random.default_rng(noise_seed))
        noise_variance = noise.variance(clean)

    ds = images.copy()
    ds["radiance"] = ds["radiance"].copy(data=measured)
    ds["radiance"].attrs["long_name"] = "measured pixel-averaged radiance"
    ds["radiance_std_error"].attrs["long_name"] = (
        "Monte Carlo standard error of the rendered (noise-free) radiance"
    )
    ds["radiance_noise_std"] = (IMAGE_DIMS, np.sqrt(noise_variance + mc_variance))
    ds["radiance_noise_std"].attrs.update(
        units=RADIANCE_UNITS,
        long_name="expected standard deviation of the measured radiance",
        comment="camera noise of the noise model and Monte Carlo error, in quadrature",
    )
    ds.attrs.update(
        title="cloudct measurements",
        wavelength=float(wavelength),
        wavelength_units="micron",
        medium_box=np.array([v for e in edges for v in (e[0], e[-1])], dtype=float),
        medium_box_note="x_min, x_max, y_min, y_max, z_min, z_max of the medium [km]",
        medium_shape=np.array([len(e) - 1 for e in edges], dtype=np.int32),
        medium_source=str(medium.attrs.get("source", "")),
        **_noise_attrs(noise, noise_seed),
    )
    family, mode = transmittance_model(medium)
    if mode is not None:
        ds.attrs["transmittance"] = family
        ds["transmittance_mode"] = mode
    return ds


def measured_transmittance(measurements: xr.Dataset) -> tuple[str, xr.DataArray | None]:
    """The transmittance family the measurements were made under and its mode (a scalar or
    a field over the medium's x, y, z): ``("exponential", None)`` where they record none."""
    family = str(measurements.attrs.get("transmittance", "exponential"))
    if family != "exponential" and "transmittance_mode" not in measurements:
        raise MeasurementError(f"the measurements' transmittance {family!r} has no "
                               "transmittance_mode variable")
    return family, (None if family == "exponential" else measurements["transmittance_mode"])


def assumed_transmittance(initial: xr.Dataset, measurements: xr.Dataset, assumption: str
                          ) -> xr.Dataset:
    """A retrieval's initial medium under its transmittance ``assumption``: ``"exponential"``
    drops any model the medium carries (with a warning), ``"medium"`` gives it the
    measurements' family and mode (:func:`measured_transmittance`), a field of which must
    lie on the medium's grid."""
    family, mode = measured_transmittance(measurements)
    if assumption == "exponential":
        if transmittance_model(initial)[0] != "exponential":
            warnings.warn("the initial medium's non-exponential transmittance is dropped: the "
                          "retrieval assumes the exponential (transmittance 'medium' keeps "
                          "the measurements' model)", stacklevel=3)
        if family != "exponential":
            warnings.warn(f"the measurements were made under the {family!r} transmittance; "
                          "the retrieval assumes the exponential (transmittance 'medium' "
                          "retrieves under theirs)", stacklevel=3)
        return with_transmittance(initial, "exponential")
    if family == "exponential":
        warnings.warn("the measurements record no non-exponential transmittance: the "
                      "retrieval under their model assumes the exponential", stacklevel=3)
    try:
        return with_transmittance(initial, family, mode)
    except MediumError as err:
        raise ValueError(f"the measurements' transmittance mode does not fit the initial "
                         f"medium: {err}") from err


def _noise_attrs(noise: NoiseModel | None, noise_seed: int) -> dict:
    """The noise model as netCDF attributes (``noise_model = "none"`` without noise)."""
    if noise is None:
        return {"noise_model": "none"}
    return {
        "noise_model": "poisson+gaussian",
        "noise_electrons": float(noise.electrons),
        "noise_reference_radiance": float(noise.reference_radiance),
        "noise_read_electrons": float(noise.read_noise),
        "noise_seed": int(noise_seed),
        "noise_note": (
            "mean photo-electrons = noise_electrons * radiance / noise_reference_radiance, "
            "Poisson; plus Gaussian read noise of noise_read_electrons rms"
        ),
    }


def noise_model_from_attrs(ds: xr.Dataset) -> NoiseModel | None:
    """The noise model recorded in a measurement set (None for noise-free measurements)."""
    if ds.attrs.get("noise_model", "none") == "none":
        return None
    return NoiseModel(
        electrons=float(ds.attrs["noise_electrons"]),
        read_noise=float(ds.attrs["noise_read_electrons"]),
        reference_radiance=float(ds.attrs["noise_reference_radiance"]),
    )


def validate_measurements(ds: xr.Dataset, *, bands: bool = False) -> None:
    """Check a measurement set; raise :class:`MeasurementError` naming the problem.

    With ``bands`` a set with several bands (a ``band`` dimension) is checked as such
    (:func:`_validate_bands`); without, as the readers that take one band (carving, the
    retrieval) call it, such a set is refused with a line saying how to take one band out
    (:func:`band_measurements`). A set without a ``band`` dimension is checked alike.

    Required: ``radiance`` over (view, row, col), finite or NaN (NaN marks a masked pixel;
    not all pixels masked); the camera variables (``position``, ``lookat``, ``up``, ``fov``,
    ``nrows``, ``ncols``) agreeing with the image size; the scene attributes
    (``sun_zenith``, ``sun_azimuth``, ``boundary``). ``radiance_noise_std`` and
    ``radiance_std_error``, when present, must have the images' shape and be finite and
    >= 0; ``wavelength``, when present, must be positive; a recorded transmittance model
    (``transmittance``, ``transmittance_mode``) must be one a medium may hold.
    """
    if BAND in ds.dims:
        if not bands:
            raise MeasurementError(_one_band_only(ds))
        _validate_bands(ds)
        return
    if "radiance" not in ds:
        raise MeasurementError("measurements have no 'radiance' variable")
    radiance = ds["radiance"]
    if radiance.dims != IMAGE_DIMS:
        raise MeasurementError(f"radiance must be over {IMAGE_DIMS}, got {radiance.dims}")
    values = radiance.values
    if np.any(np.isinf(values)):
        raise MeasurementError("radiance has infinite values (use NaN to mask a pixel)")
    if np.all(np.isnan(values)):
        raise MeasurementError("every radiance pixel is NaN (masked)")
    missing = [a for a in SCENE_ATTRS if a not in ds.attrs]
    if missing:
        raise MeasurementError(f"scene attributes missing: {', '.join(missing)}")
    for name, unit in _UNITS.items():
        problem = units_problem(name, ds[name].attrs["units"], unit) if (
            name in ds and "units" in ds[name].attrs) else None
        if problem is not None:
            raise MeasurementError(problem)
    try:
        cameras = cameras_from_dataset(ds)
        Scene.from_dataset(ds)
    except ValueError as err:
        raise MeasurementError(f"bad cameras or scene: {err}") from err
    shape = values.shape
    if len(cameras) != shape[0]:
        raise MeasurementError(f"{len(cameras)} cameras but {shape[0]} views of radiance")
    for i, cam in enumerate(cameras):
        if (cam.nrows, cam.ncols) != shape[1:]:
            raise MeasurementError(
                f"camera {i} has {cam.nrows}x{cam.ncols} pixels, the images {shape[1]}x{shape[2]}"
            )
    for name in ("radiance_noise_std", "radiance_std_error"):
        if name in ds:
            error = ds[name].values
            if ds[name].dims != IMAGE_DIMS or error.shape != shape:
                raise MeasurementError(f"{name} must be over {IMAGE_DIMS} like the radiance")
            if not np.all(np.isfinite(error)) or np.any(error < 0.0):
                raise MeasurementError(f"{name} must be finite and >= 0")
    if "wavelength" in ds.attrs and not float(ds.attrs["wavelength"]) > 0.0:
        raise MeasurementError(f"wavelength must be positive, got {ds.attrs['wavelength']}")
    try:
        check_transmittance(ds)
    except MediumError as err:
        raise MeasurementError(f"the recorded transmittance model: {err}") from err


def save_measurements(ds: xr.Dataset, path: str | os.PathLike, overwrite: bool = False) -> None:
    """Validate a measurement set (one band or several) and write it to netCDF-4 (moved into
    place when complete).

    Raises:
        FileExistsError: ``path`` exists and ``overwrite`` is False.
        MeasurementError: ``ds`` is not a valid measurement set.
    """
    validate_measurements(ds, bands=True)
    save_netcdf(ds, path, overwrite=overwrite)


def load_measurements(path: str | os.PathLike) -> xr.Dataset:
    """Read a measurement file fully into memory (the file is closed) and validate it.

    A file with several bands is returned as it is: :func:`band_measurements` takes one out.

    Raises:
        FileNotFoundError: no such file.
        InputFileError: the file cannot be read as netCDF (truncated, another format).
        MeasurementError: the file does not hold a valid measurement set (the message names
            the file).
    """
    return load_netcdf(path, "measurement", partial(validate_measurements, bands=True))


def coarse_measurements(measurements: xr.Dataset, block: int) -> xr.Dataset:
    """Measurements of cameras with ``block`` x ``block`` times larger pixels: the block
    mean of the radiance is exactly the box-filtered radiance of the coarser pixel. The
    attributes (optics, noise model, transmittance) and a transmittance mode are kept."""
    if BAND in measurements.dims:
        raise MeasurementError(_one_band_only(measurements))
    if block == 1:
        return measurements
    scene = Scene.from_dataset(measurements)
    cam = scene.cameras[0]
    if cam.nrows % block or cam.ncols % block:
        raise ValueError(f"image size {cam.nrows}x{cam.ncols} is not divisible by {block}")
    radiance = measurements["radiance"].values
    nv, nr, nc = radiance.shape
    coarse = radiance.reshape(nv, nr // block, block, nc // block, block).mean(axis=(2, 4))
    cams = [replace(c, nrows=c.nrows // block, ncols=c.ncols // block) for c in scene.cameras]
    ds = Scene(cams, scene.sun, scene.boundary, scene.ground_albedo).to_dataset()
    ds["radiance"] = (("view", "row", "col"), coarse)
    ds["radiance"].attrs.update(measurements["radiance"].attrs)
    ds.attrs = {**measurements.attrs, **ds.attrs}
    if "transmittance_mode" in measurements:
        ds["transmittance_mode"] = measurements["transmittance_mode"]
    return ds


# --- several bands ----------------------------------------------------------------------


def band_wavelengths(measurements: xr.Dataset) -> np.ndarray:
    """The wavelengths [micron] of a measurement set's bands: its coordinate ``wavelength``
    with several bands, else its one ``wavelength`` attribute (empty where it records none)."""
    if BAND in measurements.dims and "wavelength" in measurements.variables:
        return np.asarray(measurements["wavelength"].values, dtype=float)
    if "wavelength" in measurements.attrs:
        return np.array([float(measurements.attrs["wavelength"])])
    return np.array([])


def _listing(wavelengths) -> str:  # "0.672, 1.65, 2.13"
    return ", ".join(f"{float(w):g}" for w in wavelengths)


def _one_band_only(ds: xr.Dataset) -> str:
    """The refusal of a set with several bands by a reader that takes one."""
    held = f"{ds.sizes[BAND]} bands ({_listing(band_wavelengths(ds))} micron)"
    return (f"the measurements hold {held}; this reader takes one band: take it out with "
            "band_measurements(measurements, wavelength)")


def _validate_bands(ds: xr.Dataset) -> None:
    """Check a measurement set with a ``band`` dimension (docs/measurements.md, "Bands"):
    ``radiance`` over (band, view, row, col); the coordinate ``wavelength`` over band,
    positive and increasing, instead of the attribute; the cameras and the sun (variables
    and attributes without ``band``) the same for every band; a variable over ``band`` is
    one value per band (an attribute of that band's set) or images over (band, view, row,
    col); and each band, taken out (:func:`band_measurements`), a valid one-band set."""
    if "radiance" not in ds:
        raise MeasurementError("measurements have no 'radiance' variable")
    if ds["radiance"].dims != _BAND_IMAGE_DIMS:
        raise MeasurementError(f"radiance must be over {_BAND_IMAGE_DIMS} in a set with bands, "
                               f"got {ds['radiance'].dims}")
    if "wavelength" not in ds.variables or ds["wavelength"].dims != (BAND,):
        raise MeasurementError("a set with bands needs the coordinate wavelength over band "
                               "[micron]")
    if "wavelength" in ds.attrs:
        raise MeasurementError("a set with bands gives its wavelengths as the coordinate "
                               "wavelength, not the attribute wavelength")
    if problem := units_problem("wavelength", ds["wavelength"].attrs.get("units", "um"),
                                "micron"):
        raise MeasurementError(problem)
    wavelengths = np.asarray(ds["wavelength"].values, dtype=float)
    if not (np.all(np.isfinite(wavelengths)) and np.all(wavelengths > 0.0)):
        raise MeasurementError(f"wavelengths must be positive, got {_listing(wavelengths)}")
    if np.any(np.diff(wavelengths) <= 0.0):
        raise MeasurementError("wavelengths must be distinct and increasing, got "
                               f"{_listing(wavelengths)}")
    for name, variable in ds.variables.items():
        if BAND not in variable.dims or name in ("wavelength", BAND):
            continue
        if name in CAMERA_VARIABLES or name in SCENE_ATTRS:
            raise MeasurementError(f"{name} varies over band: every band must have the same "
                                   "cameras and sun")
        if variable.dims not in ((BAND,), _BAND_IMAGE_DIMS):
            raise MeasurementError(f"{name} is over {variable.dims}: a variable over band must "
                                   f"be over ('band',) (one value per band) or "
                                   f"{_BAND_IMAGE_DIMS} (images)")
        if variable.dims == (BAND,) and name in ds.attrs:
            raise MeasurementError(f"{name} is both an attribute and a variable over band")
    for name in ("radiance_noise_std", "radiance_std_error"):
        if name in ds and ds[name].dims != _BAND_IMAGE_DIMS:
            raise MeasurementError(f"{name} must be over {_BAND_IMAGE_DIMS} like the radiance")
    for i, wavelength in enumerate(wavelengths):
        try:
            validate_measurements(_band_at(ds, i))
        except MeasurementError as err:
            raise MeasurementError(f"band {wavelength:g} micron: {err}") from None


def _band_at(ds: xr.Dataset, i: int) -> xr.Dataset:
    """Band ``i`` of a set with bands in the one-band layout: the images' band taken, the
    wavelength and the other variables over ``band`` alone made attributes."""
    one = ds.isel({BAND: i})
    per_band = [name for name, v in ds.variables.items() if v.dims == (BAND,) and name != BAND]
    attrs = dict(ds.attrs)
    for name in per_band:  # as a Python number or string
        value = one[name].values
        attrs[name] = str(value.item()) if value.dtype.kind in "USO" else value.item()
    attrs["wavelength"] = float(attrs["wavelength"])
    one = one.drop_vars([*per_band, *([BAND] if BAND in one.variables else [])])
    one.attrs = attrs
    return one


def band_measurements(
    measurements: xr.Dataset, wavelength: float, tolerance: float = BAND_TOLERANCE
) -> xr.Dataset:
    """The one band of ``measurements`` at ``wavelength`` [micron] in the one-band layout
    (images over (view, row, col), the wavelength and the band's own values as attributes):
    the band nearest it, which must lie within ``tolerance`` [micron]. A set without bands
    is returned as it is where its ``wavelength`` attribute (if any) lies within
    ``tolerance``. :func:`cloudct.measurement_bands.stack_bands` is the inverse.

    Raises:
        MeasurementError: no band within ``tolerance`` (the message lists the bands).
    """
    wavelength = float(wavelength)
    held = band_wavelengths(measurements)
    if BAND not in measurements.dims:
        if held.size and abs(held[0] - wavelength) > tolerance:
            raise MeasurementError(f"no band at {wavelength:g} micron: the measurements hold "
                                   f"one band, {held[0]:g} micron")
        return measurements
    i = int(np.argmin(np.abs(held - wavelength)))
    if not abs(held[i] - wavelength) <= tolerance:
        raise MeasurementError(f"no band at {wavelength:g} micron (within {tolerance:g}): the "
                               f"measurements hold {_listing(held)} micron")
    return _band_at(measurements, i)
