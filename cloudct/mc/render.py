"""Render multi-view images of a medium: the Python API and the ``cloudct render`` command.

:func:`render` runs the forward (sun -> cameras, local estimation), the backward
(cameras -> sun, next-event estimation) or the combined estimator (both, each path weighted
by multiple importance sampling: :mod:`cloudct.mc.combined`) and returns an ``xarray.Dataset`` of
``radiance`` and ``radiance_std_error`` over (view, row, col), with the cameras as
variables over ``view`` and the sun, boundary and run statistics as attributes.

Photons (forward) or pixel samples (backward) are split into ``batches`` independent
batches (the combined estimator: both, batch b of its images the sum of the two estimators'
batch b); the image is the mean over all of them and its standard error is the standard
deviation of the batch means over sqrt(batches). The batches, and so the images, do not
depend on the number of threads.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import xarray as xr

from cloudct.mc.combined import samples_per_pixel
from cloudct.mc.estimate import (
    KernelInputs,
    Sampling,
    batch_means,
    combined_inputs,
    has_peak,
    kernel_inputs,
    mean_and_std_error,
    medium_arrays,
)
from cloudct.mc.executor import BatchExecutor
from cloudct.mc.forward import RENDER
from cloudct.mc.scene import Scene
from cloudct.mc.sun import check_cloud_share
from cloudct.netcdf import save_netcdf
from cloudct.optics import DEFAULT_OPTICS, PHASE_TRUNCATION, optics_name, to_optical
from cloudct.output_files import save_figure, written_whole

RADIANCE_UNITS = "1"  # in units of the solar irradiance perpendicular to the rays, per sr
METHODS = ("forward", "backward", "combined")


def render(
    medium: xr.Dataset,
    scene: Scene,
    *,
    photons: int = 1_000_000,
    method: str = "forward",
    seed: int = 0,
    batches: int = 32,
    rr_depth: int = 100,
    rr_survival: float = 0.95,
    aim_fraction: float | None = None,
    progress: bool | None = None,
    backend: str = "cpu",
    executor: BatchExecutor | None = None,
    entry_cloud_share: float = 0.0,
    pixel_samples: int | None = None,
) -> xr.Dataset:
    """Images of ``medium`` seen by the cameras of ``scene``.

    Parameters
    ----------
    medium
        A medium Dataset (optical, or microphysical: converted with the default optics).
    scene
        Cameras, sun, boundary conditions and ground.
    photons
        Forward and combined: the number of photons. Backward: the number of samples per
        pixel. Rounded up to a multiple of ``batches``.
    method
        ``"forward"`` (local estimation, one path serves every view), ``"backward"``, or
        ``"combined"``: both, each path's estimate weighted by its share under multiple
        importance sampling (:mod:`cloudct.mc.combined`), so that neither estimator's
        fireflies survive where the other samples the phase function's peak: for Mie
        optics.
    seed
        Seed of the counter-based random streams: same seed, same images.
    batches
        Independent batches for the standard errors (at least 2).
    rr_depth, rr_survival
        Russian roulette: from vertex ``rr_depth`` on a path survives each vertex with
        probability ``rr_survival`` (medium-independent, unbiased).
    aim_fraction
        The share of scattering events whose new direction is drawn around the direction
        to a camera that sees them (forward paths) or to the sun (backward paths), with
        the weight that keeps the images unbiased (directional importance sampling,
        :mod:`cloudct.mc.detector_sampling`). It tames the fireflies of peaked (Mie) phase
        functions; 0 switches it off; None (default): 0.1 with tabulated (Mie) phase
        functions, else 0 (:func:`default_aim_fraction`).
    progress
        Show a progress bar (None: only on a terminal).
    backend
        ``"cpu"``, ``"cuda"`` or ``"auto"`` (CUDA where a GPU is available, else the CPU
        with a warning); see :mod:`cloudct.mc.backend`. Same seed, same random streams.
    executor
        Traces the batches elsewhere (:class:`~cloudct.mc.executor.BatchExecutor`), e.g.
        a :class:`cloudct.distributed.DaskExecutor` on Dask workers (``backend`` resolved
        there), with bitwise the same result. None: this process.
    entry_cloud_share
        Forward: the share m in [0, 1) of photons that enter the box where the sun's rays
        meet clouds (in proportion to 1 - exp(-tau) of the entry cell's ray), the rest
        uniformly, each photon weighted so that the images stay unbiased
        (:mod:`cloudct.mc.sun`). 0 (default): uniform entry, bitwise the images of
        earlier versions. The backward estimator ignores it. The share applied is the
        images' attribute ``entry_cloud_share`` (0 where no ray of the sun meets
        extinction: uniform entry).
    pixel_samples
        Combined: the backward samples per pixel, rounded up to a multiple of
        ``batches``; None: :func:`default_pixel_samples`. Other methods refuse it. The
        combined images' attributes add ``pixel_samples``, ``mis_ratio`` (backward samples
        per pixel over photons) and ``backward_share`` (the share of the images' light
        that the backward paths carry).

    Examples
    --------
    A cube of 20 /km, 200 m on a side, seen from 2 km above with the sun at the zenith:

    >>> import numpy as np
    >>> from cloudct.mc.cameras import Camera
    >>> from cloudct.mc.scene import Scene
    >>> from cloudct.mc.sun import Sun
    >>> from cloudct.medium import optical_medium
    >>> centres = np.linspace(0.01, 0.19, 10)  # km
    >>> cube = optical_medium(centres, centres, centres, np.full((10, 10, 10), 20.0))
    >>> camera = Camera((0.1, 0.1, 2.0), (0.1, 0.1, 0.1), up=(0, 1, 0), fov=10.0,
    ...                 nrows=8, ncols=8)
    >>> images = render(cube, Scene([camera], sun=Sun(zenith=0.0)), photons=20_000,
    ...                 progress=False)
    >>> images["radiance"].dims, images["radiance"].shape
    (('view', 'row', 'col'), (1, 8, 8))
    >>> radiance = images["radiance"].values[0]
    >>> float(radiance[0, 0]), bool(radiance[3:5, 3:5].min() > 0.0)  # sky, cloud
    (0.0, True)
    """
    images, info = render_batches(
        medium, scene, photons=photons, method=method, seed=seed, batches=batches,
        rr_depth=rr_depth, rr_survival=rr_survival, aim_fraction=aim_fraction,
        progress=progress, backend=backend, executor=executor,
        entry_cloud_share=entry_cloud_share, pixel_samples=pixel_samples,
    )
    radiance, std_error = mean_and_std_error(images)
    return images_dataset(radiance, std_error, scene, optics=optics_name(medium), **info)


def render_batches(
    medium: xr.Dataset,
    scene: Scene,
    *,
    photons: int,
    method: str = "forward",
    seed: int = 0,
    batches: int = 32,
    rr_depth: int = 100,
    rr_survival: float = 0.95,
    aim_fraction: float | None = None,
    progress: bool | None = None,
    backend: str = "cpu",
    executor: BatchExecutor | None = None,
    entry_cloud_share: float = 0.0,
    pixel_samples: int | None = None,
) -> tuple[np.ndarray, dict]:
    """The images of each independent batch, float64[batches, view, row, col], and the run's
    attributes; :func:`render` averages them. Arguments as for :func:`render`."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if pixel_samples is not None and method != "combined":
        raise ValueError(f"pixel_samples is the combined estimator's; method {method!r} "
                         f"takes its samples from photons")
    sampling = Sampling(batches, seed, rr_depth, rr_survival, backend)
    per_batch = sampling.per_batch(photons)
    check_cloud_share(entry_cloud_share)
    forward = method != "backward"
    k = kernel_inputs(medium, scene, aim_fraction,
                      entry_cloud_share=entry_cloud_share if forward else 0.0)
    run_of = dict(progress=progress, executor=executor, sampling=sampling)
    extra = {}
    if method == "combined":
        if pixel_samples is None:
            pixel_samples = default_pixel_samples(per_batch * batches, scene)
        k, per_pixel = combined_inputs(k, sampling, per_batch, pixel_samples)
        images, run = batch_means("forward", k, (RENDER, None), per_batch=per_batch,
                                  desc="combined, forward", **run_of)
        backward, run_backward = backward_images(k, per_pixel, **run_of)
        total = float(images.sum() + backward.sum())
        images += backward
        run = {**run_backward, **run, "events": run["events"] + run_backward["events"],
               "wall_time": run["wall_time"] + run_backward["wall_time"]}
        extra = dict(pixel_samples=per_pixel * batches, mis_ratio=k.cams.mis_ratio,
                     backward_share=float(backward.sum()) / total if total > 0.0 else 0.0)
    elif forward:
        images, run = batch_means("forward", k, (RENDER, None), per_batch=per_batch,
                                  desc=method, **run_of)
    else:
        images, run = batch_means("backward", k, (), per_batch=per_batch, desc=method,
                                  **run_of)
    info = dict(
        method=method, photons=per_batch * batches, **extra, seed=seed, batches=batches,
        rr_depth=rr_depth, rr_survival=rr_survival, aim_fraction=k.cams.aim_fraction,
        entry_cloud_share=k.sun.cloud_share,
        phase_truncation=float(medium.attrs.get(PHASE_TRUNCATION, 0.0)), **run,
    )
    return images, info


def default_method(medium: xr.Dataset) -> str:
    """The estimator for images that are to be as good as they can (synthetic measurements):
    ``"combined"`` for a medium with a tabulated (Mie) phase function, whose diffraction peak
    gives the forward images fireflies that the combined estimator removes (measured:
    docs/benchmarks.md, "Mie optics"), else ``"forward"``."""
    return "combined" if has_peak(medium_arrays(medium)[1]) else "forward"


def backward_images(
    k: KernelInputs, per_pixel: int, **run_of
) -> tuple[np.ndarray, dict]:
    """The combined estimator's backward half of the images, per batch: ``per_pixel``
    samples of every pixel in each batch, each next-event estimate weighted by w_b
    (``k.cams.mis_ratio`` > 0; :func:`combined_inputs`). ``run_of``: ``sampling``,
    ``progress``, ``executor`` of :func:`~cloudct.mc.estimate.batch_means`."""
    return batch_means("backward", k, (), per_batch=per_pixel, desc="combined, backward",
                       **run_of)


def default_pixel_samples(photons: int, scene: Scene) -> int:
    """The combined estimator's backward samples per pixel when none are given:
    :data:`~cloudct.mc.combined.BACKWARD_PATHS_PER_PHOTON` backward paths per forward
    photon, spread over the scene's pixels (at least 1 per pixel)."""
    cam = scene.cameras[0]
    return samples_per_pixel(photons, len(scene.cameras) * cam.nrows * cam.ncols)


def images_dataset(
    radiance: np.ndarray, std_error: np.ndarray, scene: Scene, **run_attrs
) -> xr.Dataset:
    """Images and their standard errors as a Dataset carrying the scene."""
    dims = ("view", "row", "col")
    ds = scene.to_dataset()
    ds["radiance"] = (dims, radiance)
    ds["radiance"].attrs.update(
        units=RADIANCE_UNITS,
        long_name="pixel-averaged radiance",
        comment="normalised so that the solar irradiance perpendicular to the rays is 1",
    )
    ds["radiance_std_error"] = (dims, std_error)
    ds["radiance_std_error"].attrs.update(
        units=RADIANCE_UNITS, long_name="Monte Carlo standard error of the radiance"
    )
    ds = ds.assign_coords(row=np.arange(radiance.shape[1]), col=np.arange(radiance.shape[2]))
    ds["row"].attrs.update(long_name="image row, 0 at the top")
    ds["col"].attrs.update(long_name="image column, 0 at the left")
    ds.attrs.update(title="cloudct rendered images", **run_attrs)
    return ds


def save_images(images: xr.Dataset, path: str | Path, overwrite: bool = False) -> None:
    """Write rendered images to netCDF (refusing to overwrite unless asked)."""
    save_netcdf(images, path, overwrite=overwrite)


def save_previews(images: xr.Dataset, directory: str | Path) -> list[Path]:
    """PNG previews: one per view and a mosaic of all views; returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    radiance = images["radiance"].values
    vmax = float(radiance.max()) or 1.0
    written = []
    for v in range(radiance.shape[0]):
        path = directory / f"view{v:02d}.png"
        with written_whole(path) as partial:
            plt.imsave(partial, radiance[v], cmap="gray", vmin=0.0, vmax=vmax)
        written.append(path)
    n = radiance.shape[0]
    ncol = math.ceil(math.sqrt(n))
    nrow = math.ceil(n / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(2.4 * ncol, 2.4 * nrow), squeeze=False)
    for k, ax in enumerate(axes.flat):
        ax.axis("off")
        if k < n:
            ax.imshow(radiance[k], cmap="gray", vmin=0.0, vmax=vmax)
            ax.set_title(f"view {k}", fontsize=8)
    fig.suptitle(f"radiance ({images.attrs.get('method', '')}), common scale 0..{vmax:.3g}")
    fig.tight_layout()
    path = directory / "views.png"
    save_figure(fig, path, dpi=120)
    plt.close(fig)
    written.append(path)
    return written


def single_cloud_medium(optics: str = DEFAULT_OPTICS) -> xr.Dataset:
    """The seed paper's single cloud (bundled rico32x37x26) with the named cloud ``optics``
    (:func:`cloudct.optics.to_optical`; the default, ``"hg"``, is the paper's: Mie
    extinction at 0.672 micron, HG g = 0.85, cloud albedo 0.99), air 0.04 /km with albedo
    0.912. ``cloudct les2nc`` of the bundled file gives the same medium for the same
    optics."""
    from cloudct.les import bundled_single_cloud

    return to_optical(bundled_single_cloud(), optics=optics)
