"""Render multi-view images of a medium: the Python API and the ``cloudct render`` command.

:func:`render` runs the forward (sun -> cameras, local estimation) or the backward
(cameras -> sun, next-event estimation) estimator and returns an ``xarray.Dataset`` of
``radiance`` and ``radiance_std_error`` over (view, row, col), with the cameras as
variables over ``view`` and the sun, boundary and run statistics as attributes.

Photons (forward) or pixel samples (backward) are split into ``batches`` independent
batches; the image is the mean over all of them and its standard error is the standard
deviation of the batch means over sqrt(batches). The batches, and so the images, do not
depend on the number of threads.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np
import xarray as xr
from tqdm.auto import tqdm

from cloudct.mc.backend import backward_runner, forward_runner, resolve_backend
from cloudct.mc.cameras import CameraArrays, camera_arrays
from cloudct.mc.detector_sampling import DEFAULT_AIM_FRACTION
from cloudct.mc.forward import RENDER
from cloudct.mc.scene import (
    BOUNDARIES,
    PRESETS,
    Scene,
    build_scene,
    check_scene,
    load_scene,
    periodic_copy_ranges,
    single_cloud_scene,
)
from cloudct.mc.sun import SunArrays, sun_arrays
from cloudct.medium import cell_edges, is_optical, load_medium, validate_medium
from cloudct.physics.mixing import OpticalGrid
from cloudct.physics.optics import kernel_arrays, to_optical
from cloudct.physics.phase import TABULATED, PhaseBank

RADIANCE_UNITS = "1"  # in units of the solar irradiance perpendicular to the rays, per sr
METHODS = ("forward", "backward")


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
    client=None,
) -> xr.Dataset:
    """Images of ``medium`` seen by the cameras of ``scene``.

    Parameters
    ----------
    medium
        A medium Dataset (optical, or microphysical: converted with the default optics).
    scene
        Cameras, sun, boundary conditions and ground.
    photons
        Forward: the number of photons. Backward: the number of samples per pixel.
        Rounded up to a multiple of ``batches``.
    method
        ``"forward"`` (local estimation, one path serves every view) or ``"backward"``.
    seed
        Seed of the counter-based random streams: same seed, same images.
    batches
        Independent batches for the standard errors (at least 2).
    rr_depth, rr_survival
        Russian roulette: from vertex ``rr_depth`` on a path survives each vertex with
        probability ``rr_survival`` (medium-independent, unbiased).
    aim_fraction
        Forward: the share of scattering events whose new direction is drawn around the
        direction to a camera that sees them, with the weight that keeps the images
        unbiased (detector directional importance sampling,
        :mod:`cloudct.mc.detector_sampling`). It tames the fireflies of peaked (Mie) phase
        functions; 0 switches it off; None (default): 0.1 with tabulated (Mie) phase
        functions, else 0 (:func:`default_aim_fraction`). The backward estimator ignores
        it.
    progress
        Show a progress bar (None: only on a terminal).
    backend
        ``"cpu"``, ``"cuda"`` or ``"auto"`` (CUDA where a GPU is available, else the CPU
        with a warning); see :mod:`cloudct.mc.backend`. Same seed, same random streams.
    client
        A Dask client, scheduler address or :class:`cloudct.distributed.DaskExecutor`:
        the batches are traced on its workers (``backend`` resolved there), with bitwise
        the same result (see :mod:`cloudct.distributed`). None: this process.
    """
    batch_means, info = render_batches(
        medium, scene, photons=photons, method=method, seed=seed, batches=batches,
        rr_depth=rr_depth, rr_survival=rr_survival, aim_fraction=aim_fraction,
        progress=progress, backend=backend, client=client,
    )
    radiance = batch_means.mean(axis=0)
    std_error = batch_means.std(axis=0, ddof=1) / math.sqrt(batches)
    return images_dataset(radiance, std_error, scene, **info)


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
    client=None,
) -> tuple[np.ndarray, dict]:
    """The images of each independent batch, float64[batches, view, row, col], and the run's
    attributes; :func:`render` averages them. Arguments as for :func:`render`."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    check_sampling(photons, batches, rr_depth, rr_survival)
    k = kernel_inputs(medium, scene, aim_fraction if method == "forward" else 0.0)
    per_batch = math.ceil(int(photons) / batches)
    if client is not None:
        from cloudct.distributed.core import render_batch_means

        return render_batch_means(
            client, k, method=method, seed=seed, per_batch=per_batch, batches=batches,
            rr_depth=rr_depth, rr_survival=rr_survival, backend=backend, progress=progress,
        )
    images = np.zeros((batches, len(scene.cameras), k.cams.nrows, k.cams.ncols))
    events = np.zeros(batches, dtype=np.int64)
    no_residual = np.zeros((1, 1, 1))
    no_gradients = np.zeros((batches, 1, 1, 1))

    backend = resolve_backend(backend)
    if method == "forward":
        run = forward_runner(
            backend, k, rr_depth, rr_survival, seed, per_batch, RENDER, images, no_residual,
            no_gradients, events,
        )
    else:
        run = backward_runner(backend, k, rr_depth, rr_survival, seed, per_batch, images, events)

    unit = "photon" if method == "forward" else "sample/px"
    wall = run_in_rounds(
        run, per_batch, batches, progress, unit=unit, desc=method, max_rounds=run.max_rounds
    )

    info = dict(
        method=method, photons=per_batch * batches, seed=seed, batches=batches,
        events=int(events.sum()), wall_time=wall, rr_depth=rr_depth, rr_survival=rr_survival,
        aim_fraction=k.cams.aim_fraction, backend=backend,
    )
    return images / per_batch, info


def check_sampling(samples: int, batches: int, rr_depth: int, rr_survival: float) -> None:
    """Refuse sample counts, batch counts and Russian-roulette settings that cannot work."""
    if int(samples) < 1:
        raise ValueError(f"photons (samples) must be a positive count, got {samples}")
    if int(batches) < 2:
        raise ValueError(f"batches must be at least 2 for standard errors, got {batches}")
    if not 0.0 < rr_survival <= 1.0 or rr_depth < 1:
        raise ValueError("rr_survival must be in (0, 1] and rr_depth >= 1")


def check_residual(residual: np.ndarray, scene: Scene) -> np.ndarray:
    """The residual weights as a float64 (view, row, col) array matching the scene."""
    residual = np.ascontiguousarray(residual, dtype=np.float64)
    cam = scene.cameras[0]
    shape = (len(scene.cameras), cam.nrows, cam.ncols)
    if residual.shape != shape:
        raise ValueError(f"residual has shape {residual.shape}, the scene's images {shape}")
    if not np.all(np.isfinite(residual)):
        raise ValueError("residual has NaN or infinite pixels (mask them with weight 0)")
    return residual


class KernelInputs(NamedTuple):
    """Everything the kernels need of a medium and a scene."""

    grid: OpticalGrid
    bank: PhaseBank
    cams: CameraArrays
    copies: np.ndarray
    sun: SunArrays
    periodic: bool
    ground: float  # ground albedo, -1 for no ground
    edges: tuple[np.ndarray, np.ndarray, np.ndarray]


def kernel_inputs(
    medium: xr.Dataset, scene: Scene, aim_fraction: float | None = None
) -> KernelInputs:
    """Validate a medium and a scene and gather them into kernel arrays (``aim_fraction``:
    the forward estimator's detector directional importance sampling, see
    :mod:`cloudct.mc.detector_sampling`; 0 switches it off, None chooses it by the optics:
    :func:`default_aim_fraction`)."""
    validate_medium(medium)
    optical = medium if is_optical(medium) else to_optical(medium)
    grid, bank = kernel_arrays(optical)
    edges = cell_edges(optical)
    check_scene(scene, edges)
    if aim_fraction is None:
        aim_fraction = default_aim_fraction(bank)
    return KernelInputs(
        grid=grid,
        bank=bank,
        cams=camera_arrays(scene.cameras, aim_fraction),
        copies=periodic_copy_ranges(scene, edges),
        sun=sun_arrays(scene.sun, edges, scene.periodic),
        periodic=scene.periodic,
        ground=-1.0 if scene.ground_albedo is None else float(scene.ground_albedo),
        edges=edges,
    )


def default_aim_fraction(bank: PhaseBank) -> float:
    """The aim fraction used when none is given: :data:`DEFAULT_AIM_FRACTION` when a phase
    function is tabulated (Mie optics, whose diffraction peak makes fireflies), else 0
    (Henyey-Greenstein and Rayleigh: measured in docs/benchmarks.md, "Mie optics")."""
    return DEFAULT_AIM_FRACTION if np.any(bank.kind == TABULATED) else 0.0


def run_in_rounds(
    run: Callable[[int, int], None], per_batch: int, batches: int, progress: bool | None,
    unit: str, desc: str, max_rounds: int = 50,
) -> float:
    """Call ``run(first, last)`` over up to ``max_rounds`` rounds of the per-batch sample
    range, with a progress bar; returns the wall time in seconds."""
    rounds = np.unique(
        np.linspace(0, per_batch, min(per_batch, max_rounds) + 1).astype(np.int64)
    )
    disable = None if progress is None else not progress
    start = time.perf_counter()
    with tqdm(total=per_batch * batches, disable=disable, unit=unit, desc=desc) as bar:
        for first, last in zip(rounds[:-1], rounds[1:], strict=True):
            run(int(first), int(last))
            bar.update(int(last - first) * batches)
    return time.perf_counter() - start


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
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists (use overwrite=True / --overwrite)")
    images.to_netcdf(path)


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
        plt.imsave(path, radiance[v], cmap="gray", vmin=0.0, vmax=vmax)
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
    fig.savefig(path, dpi=120)
    plt.close(fig)
    written.append(path)
    return written


def single_cloud_medium() -> xr.Dataset:
    """The seed paper's single cloud (bundled rico32x37x26) with its optics: Mie extinction
    at 0.672 micron, cloud albedo 0.99 and HG g = 0.85, air 0.04 /km with albedo 0.912."""
    from data_synth.les import bundled_single_cloud

    optical = to_optical(bundled_single_cloud(), phase="hg", g=0.85)
    optical["cloud_albedo"] = xr.full_like(optical["cloud_extinction"], 0.99).assign_attrs(
        units="1", long_name="cloud single-scattering albedo"
    )
    return optical


def _cli_render(args: argparse.Namespace) -> int:
    """``cloudct render``: images of a medium for a scene, to netCDF and PNG previews."""
    if args.medium is None:
        medium = single_cloud_medium()
    else:
        medium = load_medium(args.medium)
    if args.scene is None:
        edges = cell_edges(medium)
        scene = single_cloud_scene(
            np.array([e[0] for e in edges]), np.array([e[-1] for e in edges])
        )
    else:
        scene = load_scene(args.scene)
    output = Path(args.output)
    if output.exists() and not args.overwrite:
        raise FileExistsError(f"{output} exists (use --overwrite)")
    client = None
    if args.scheduler is not None or args.workers is not None:
        from cloudct.distributed.core import close_client, connect

        client = connect(args.scheduler, args.workers, backend=args.backend)
    try:
        # compile (or load from the numba cache) first, so that the reported rate is the
        # render's
        render(medium, scene, photons=2, method=args.method, batches=2, progress=False,
               backend=args.backend, client=client)
        images = render(
            medium, scene, photons=args.photons, method=args.method, seed=args.seed,
            batches=args.batches, aim_fraction=args.aim_fraction, progress=None,
            backend=args.backend, client=client,
        )
    finally:
        if client is not None:
            close_client(client)
    save_images(images, output, overwrite=args.overwrite)
    previews = save_previews(images, args.png or output.with_suffix(""))
    rate = images.attrs["photons"] / images.attrs["wall_time"]
    where = ""
    if "workers" in images.attrs:
        where = (f", {images.attrs['workers']} workers, "
                 f"{images.attrs['bytes_to_workers'] / 2**20:.3g} MiB out, "
                 f"{images.attrs['bytes_from_workers'] / 2**20:.3g} MiB back")
    print(
        f"wrote {output} and {len(previews)} PNG previews in {previews[0].parent} "
        f"({images.attrs['photons']} {'photons' if args.method == 'forward' else 'samples/px'}, "
        f"{images.attrs['wall_time']:.1f} s, {rate:.3g}/s{where})"
    )
    return 0


def _cli_scene(args: argparse.Namespace) -> int:
    """``cloudct scene``: write a nine-camera scene for a medium (preset and overrides)."""
    medium = single_cloud_medium() if args.medium is None else load_medium(args.medium)
    edges = cell_edges(medium)
    scene = build_scene(
        np.array([e[0] for e in edges]), np.array([e[-1] for e in edges]),
        preset=args.preset, ring_zenith=args.ring_zenith, distance=args.distance,
        altitude=args.altitude, azimuths=args.azimuths, npix=args.npix, fov=args.fov,
        sun_zenith=args.sun_zenith, sun_azimuth=args.sun_azimuth, boundary=args.boundary,
        ground_albedo=args.ground_albedo,
    )
    output = Path(args.output)
    if output.exists() and not args.overwrite:
        raise FileExistsError(f"{output} exists (use --overwrite)")
    scene.to_dataset().to_netcdf(output)
    written = f"wrote {output} ({len(scene.cameras)} cameras)"
    if args.figure:
        from cloudct.mc.scene_figure import save_scene_figure

        figure = save_scene_figure(scene, [e[0] for e in edges], [e[-1] for e in edges],
                                   args.figure)
        written += f" and {figure}"
    print(written)
    return 0


def add_distributed_options(p: argparse.ArgumentParser) -> None:
    """``--backend``, ``--workers`` and ``--scheduler`` (see docs/distributed.md)."""
    p.add_argument("--backend", choices=("cpu", "cuda", "auto"), default="cpu",
                   help="compute back end (on the workers, with --workers/--scheduler)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, metavar="N",
                       help="trace on a local Dask cluster of N worker processes (one per "
                       "GPU with --backend cuda); needs cloudct[distributed]")
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="trace on the Dask cluster of this scheduler (tcp://host:port or "
                       "a scheduler file)")


def register_cli(subparsers: argparse._SubParsersAction) -> None:
    """Add ``cloudct render`` and ``cloudct scene``."""
    p = subparsers.add_parser(
        "render",
        help="render multi-view images of a medium (default: the bundled single cloud)",
        description="Render images of a medium netCDF for a scene netCDF (default: the seed "
        "paper's single-cloud scene) to a netCDF of images plus PNG previews.",
    )
    p.add_argument("medium", nargs="?", help="medium netCDF (default: bundled single cloud)")
    p.add_argument("--scene", help="scene netCDF from `cloudct scene` (default: nine cameras)")
    p.add_argument("-o", "--output", default="images.nc", help="output netCDF of images")
    p.add_argument("--png", help="directory for PNG previews (default: next to the output)")
    p.add_argument("--photons", type=int, default=1_000_000,
                   help="forward photons, or backward samples per pixel")
    p.add_argument("--method", choices=METHODS, default="forward")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batches", type=int, default=32)
    p.add_argument("--aim-fraction", type=float, default=None, metavar="A",
                   help="forward: share of scattering directions aimed at the cameras "
                   "(unbiased; tames Mie fireflies). 0 switches it off; default 0.1 with Mie "
                   "(tabulated) phase functions, else 0")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    add_distributed_options(p)
    p.set_defaults(func=_cli_render)

    s = subparsers.add_parser(
        "scene", help="write a nine-camera scene for a medium (presets, sun, boundaries)",
        description="Write a scene netCDF: a zenith camera and a ring of eight aimed at the "
        "box centre (a ring at other azimuths or at an altitude on request). Presets: "
        "single-cloud (ring at 29 deg, 2 km, 76x76: the seed paper's single cloud), "
        "cloud-field (33 deg, 2.16 km, 86x86: its cloud field), nadir (10 deg, 1.2 x the "
        "box's horizontal diagonal, 128x128: wide domains); any number may be overridden. "
        "The field of view frames the box unless given.",
    )
    s.add_argument("medium", nargs="?", help="medium netCDF (default: bundled single cloud)")
    s.add_argument("--preset", choices=sorted(PRESETS), default="single-cloud")
    s.add_argument("--ring-zenith", type=float, metavar="DEG", help="ring cameras' zenith angle")
    where = s.add_mutually_exclusive_group()
    where.add_argument("--distance", type=float, metavar="KM",
                       help="cameras' distance from the box centre")
    where.add_argument("--altitude", type=float, metavar="KM",
                       help="every camera at this height instead (the ring farther away)")
    s.add_argument("--azimuths", type=float, nargs="+", metavar="DEG",
                   help="the ring cameras' azimuths (default: 0 45 ... 315)")
    s.add_argument("--npix", type=int, metavar="N", help="image size, N x N pixels")
    s.add_argument("--fov", type=float, metavar="DEG", help="full field of view (default: "
                   "fitted to the box)")
    s.add_argument("--sun-zenith", type=float, default=0.0, metavar="DEG")
    s.add_argument("--sun-azimuth", type=float, default=0.0, metavar="DEG",
                   help="direction towards the sun, degrees from +x toward +y")
    s.add_argument("--boundary", choices=BOUNDARIES, default="open")
    s.add_argument("--ground-albedo", type=float, metavar="A",
                   help="Lambertian ground albedo (default: no ground)")
    s.add_argument("--figure", metavar="PNG", help="also draw the scene (from above and "
                   "from the side) to this PNG file")
    s.add_argument("-o", "--output", default="scene.nc")
    s.add_argument("--overwrite", action="store_true")
    s.set_defaults(func=_cli_scene)
