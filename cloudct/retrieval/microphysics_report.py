"""The report of a retrieval of liquid water content (LWC) and droplet effective radius
(r_eff) from several bands (:mod:`cloudct.retrieval.microphysics`; ``cloudct report`` of a
result of ``cloudct retrieve --unknowns lwc reff``): the loss against iteration, summed and
per band; with a true medium, LWC's epsilon and delta (seed paper Eq. 54) and r_eff's mean
absolute and relative errors over the true cloud and over its voxels within optical
distance 5 of its lit and viewed boundary, and their curves from the run's log; slices of
both fields beside the true ones; with the measurements, each band's images beside the
result's rendered with that band's Mie table. PNG figures and a Markdown summary, as
:func:`cloudct.retrieval.report.write_report` writes for the extinction, whose figures
(:mod:`cloudct.retrieval.report_figures`) it shares."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import xarray as xr

from cloudct.mc.render import render
from cloudct.mc.scene import Scene
from cloudct.mc.visibility import boundary_optical_distance
from cloudct.measurements import BAND, MeasurementError, band_measurements
from cloudct.medium import is_microphysical, is_optical
from cloudct.optics import GRID, PHASE_TRUNCATION, band_optics, to_optical
from cloudct.physics.mie import DEFAULT_VEFF, mie_table
from cloudct.retrieval.metrics import epsilon_delta, reff_absolute_error, reff_relative_error
from cloudct.retrieval.microphysics import NEAR
from cloudct.retrieval.report import (
    configuration_lines,
    image_difference,
    priors_text,
    render_photon_count,
)
from cloudct.retrieval.report_figures import (
    Curve,
    Panel,
    curves_figure,
    images_figure,
    slices_figure,
)

#: The variables that ``cloudct report`` requires of a result of LWC and r_eff.
RESULT_VARIABLES = ("lwc", "reff", "log_loss", "log_band_loss", "wavelength")


def is_microphysical_result(result: xr.Dataset) -> bool:
    """Whether ``result`` is a retrieval of LWC and r_eff (attribute ``unknowns`` "lwc
    reff", as :meth:`cloudct.retrieval.microphysics.MicrophysicsRetrieval.result` writes)."""
    return str(result.attrs.get("unknowns", "")).split() == ["lwc", "reff"]


def _listing(wavelengths: Sequence[float]) -> str:
    return ", ".join(f"{float(w):g}" for w in wavelengths)


def true_fields(result: xr.Dataset, truth: xr.Dataset) -> tuple[np.ndarray, np.ndarray]:
    """The true LWC [g m-3] and r_eff [micron] over (x, y, z) of the medium ``truth`` for
    the ``result`` of LWC and r_eff; a ValueError in one line where ``truth`` is not
    microphysical (as :class:`~cloudct.retrieval.microphysics.MicrophysicsRetrieval`
    refuses it) or its grid is not the result's."""
    if is_optical(truth) or not is_microphysical(truth):
        raise ValueError("the result holds LWC and r_eff (cloudct retrieve --unknowns lwc "
                         "reff): its true medium must be microphysical (lwc, reff); this one "
                         "is optical (cloud extinction)")
    lwc = truth["lwc"].transpose(*GRID).values.astype(float)
    shape = result["lwc"].shape
    if lwc.shape != shape:
        raise ValueError(f"the true medium's grid ({' x '.join(map(str, lwc.shape))}) is not "
                         f"the result's ({' x '.join(map(str, shape))})")
    return lwc, truth["reff"].transpose(*GRID).values.astype(float)


def result_bands(result: xr.Dataset, measurements: xr.Dataset) -> list[xr.Dataset]:
    """The one-band measurement sets (:func:`cloudct.measurements.band_measurements`) of
    the bands the ``result`` was retrieved from (its coordinate ``wavelength``), shortest
    first; a ValueError in one line where ``measurements`` lack one."""
    wavelengths = np.sort(result["wavelength"].values.astype(float))
    try:
        return [band_measurements(measurements, w) for w in wavelengths]
    except MeasurementError as err:
        raise ValueError(f"{err}; the result was retrieved from the bands "
                         f"{_listing(wavelengths)} micron") from None


def result_tables(result: xr.Dataset, wavelengths: Sequence[float]) -> list[xr.Dataset]:
    """The Mie tables of the bands as the retrieval took them by default: each
    wavelength's :func:`~cloudct.physics.mie.mie_table` at the result's v_eff."""
    veff = float(result["veff"].max()) if "veff" in result else DEFAULT_VEFF
    return [mie_table(wavelength=float(w), veff=veff) for w in wavelengths]


def microphysics_errors(result: xr.Dataset, truth: xr.Dataset,
                        distance: np.ndarray | None = None, of: str = "") -> dict[str, float]:
    """The result's errors against ``truth`` under the keys of the run's log
    (:data:`cloudct.retrieval.microphysics.LOG_FIELDS`): ``lwc_epsilon``, ``lwc_delta``
    (:func:`~cloudct.retrieval.metrics.epsilon_delta` of LWC), ``reff_absolute_error``
    [micron], ``reff_relative_error`` over the true cloud
    (:func:`~cloudct.retrieval.metrics.reff_absolute_error`,
    :func:`~cloudct.retrieval.metrics.reff_relative_error`), and their ``_near`` variants
    over its voxels whose ``distance`` (optical distance from the cloud's lit and viewed
    boundary, :func:`boundary_distance`) is below
    :data:`~cloudct.retrieval.microphysics.NEAR` (NaN without ``distance``); of the fields
    ``lwc`` + ``of`` and ``reff`` + ``of`` (``"_average"``: the iterate average's)."""
    lwc, reff = true_fields(result, truth)
    retrieved_lwc, retrieved_reff = (result[name + of].transpose(*GRID).values.astype(float)
                                     for name in ("lwc", "reff"))
    epsilon, delta = epsilon_delta(lwc, retrieved_lwc)
    errors = {"lwc_epsilon": epsilon, "lwc_delta": delta,
              "reff_absolute_error": reff_absolute_error(lwc, reff, retrieved_reff),
              "reff_relative_error": reff_relative_error(lwc, reff, retrieved_reff)}
    near = None if distance is None else distance < NEAR
    for key, metric in (("reff_absolute_error", reff_absolute_error),
                        ("reff_relative_error", reff_relative_error)):
        errors[f"{key}_near"] = (float("nan") if near is None
                                 else metric(lwc, reff, retrieved_reff, near))
    return errors


def boundary_distance(truth: xr.Dataset, band: xr.Dataset, table: xr.Dataset) -> np.ndarray:
    """Each voxel's optical distance from the true cloud's lit and viewed boundary
    (:func:`cloudct.mc.visibility.boundary_optical_distance`) in the scene of the one-band
    measurements ``band`` at its wavelength (``table``, its Mie table): as the retrieval
    takes it for its log's ``_near`` errors, in the shortest band."""
    return boundary_optical_distance(to_optical(truth, table, optics="mie"),
                                     Scene.from_dataset(band))


def _medium(result: xr.Dataset) -> xr.Dataset:
    """The retrieved medium of a result: without its log and its mask."""
    return result.drop_dims(["iteration", BAND], errors="ignore").drop_vars(
        "cloud_mask", errors="ignore")


def write_microphysics_report(
    result: xr.Dataset,
    directory: str | Path,
    *,
    truth: xr.Dataset | None = None,
    measurements: xr.Dataset | None = None,
    render_photons: int | None = None,
    mie_tables: Sequence[xr.Dataset] | None = None,
    backend: str = "cpu",
) -> Path:
    """Write figures and ``summary.md`` for a result of LWC and r_eff
    (:func:`is_microphysical_result`) into ``directory``; returns the summary's path.

    Figures: ``loss.png`` (the loss summed over the bands and each band's against
    iteration), ``slices_lwc.png`` and ``slices_reff.png`` (beside the truth's where given,
    on one colour scale per field), with a microphysical ``truth``
    (:func:`true_fields`) ``errors.png`` (the log's LWC epsilon and delta and r_eff errors
    against iteration, where the run logged them), and with ``measurements`` holding the
    result's bands (:func:`result_bands`) ``images_<wavelength>um.png`` per band: the
    measured images above the result's, rendered with the band's Mie table
    (``mie_tables``, shortest band first; default :func:`result_tables`) by
    ``render_photons`` forward photons
    (:func:`cloudct.retrieval.report.render_photon_count`) on ``backend``. The summary
    gives the errors against the truth (:func:`microphysics_errors`; the ``_near`` ones
    need the measurements' scene) and each band's image difference
    (:func:`cloudct.retrieval.report.image_difference`)."""
    out = Path(directory)
    wavelengths = np.sort(result["wavelength"].values.astype(float))
    truth_fields = None if truth is None else true_fields(result, truth)
    bands = None if measurements is None else result_bands(result, measurements)
    tables = None
    if bands is not None:
        tables = result_tables(result, wavelengths) if mie_tables is None else list(mie_tables)
        if len(tables) != wavelengths.size:
            raise ValueError(f"{len(tables)} Mie tables for {wavelengths.size} bands")
    out.mkdir(parents=True, exist_ok=True)
    lines = ["# cloudct retrieval report: LWC and r_eff", "", *_run_lines(result, wavelengths)]
    lines += _loss_lines(result, out)
    if truth_fields is not None:
        distance = (None if bands is None
                    else boundary_distance(truth, bands[0], tables[0]))
        lines += _error_lines(result, truth, distance, out)
    lines += _slice_lines(result, truth_fields, out)
    if bands is not None:
        lines += _image_lines(result, bands, tables, render_photons, backend, out)
    lines += configuration_lines(result)
    summary = out / "summary.md"
    summary.write_text("\n".join(lines))
    return summary


def _run_lines(result: xr.Dataset, wavelengths: np.ndarray) -> list[str]:
    """The summary's opening list: the unknowns and bands, the run's length and device,
    its steps, photons, cut and bounds, its priors."""
    config = json.loads(result.attrs.get("config", "{}"))
    low, high = result.attrs.get("reff_range", (np.nan, np.nan))
    return [
        f"- unknowns: liquid water content (LWC) [g m-3] and droplet effective radius (r_eff) "
        f"[μm], from the bands {_listing(wavelengths)} μm",
        f"- iterations: {result.attrs.get('iterations_done', '?')}, wall time "
        f"{float(result.attrs.get('elapsed_s', np.nan)):.0f} s, on "
        f"{result.attrs.get('device', 'an unrecorded device')} (back end "
        f"{result.attrs.get('backend', '?')})",
        f"- steps: {config.get('lwc_step', '?')} g m-3 in LWC and {config.get('reff_step', '?')}"
        f" μm in r_eff per iteration ({config.get('optimizer', '?')}), "
        f"{_photons(result)} photons per iteration (all bands, images' and gradients'); "
        "the Mie peak cut at "
        f"{float(result.attrs.get(PHASE_TRUNCATION, 0.0)):g} degrees; r_eff kept within "
        f"{float(low):g}-{float(high):g} μm",
        f"- priors (in r_eff): {priors_text(config)}",
        "- settings: [the run's configuration](#configuration) below", "",
    ]


def _photons(result: xr.Dataset) -> str:
    """The photons of the run's last iteration, from its log."""
    logged = result["log_photons"].values if "log_photons" in result else np.array([])
    return f"{logged[-1]:.0f}" if logged.size else "?"


def _loss_lines(result: xr.Dataset, out: Path) -> list[str]:
    """The loss's section: its figure and each band's loss at the first and last
    iteration."""
    iteration = result["iteration"].values
    loss, band_loss = result["log_loss"].values, result["log_band_loss"].values
    wavelengths = result["wavelength"].values
    if not iteration.size:
        return ["## Loss", "", "The run's log is empty.", ""]
    curves = [Curve("all bands", loss),
              *(Curve(f"{w:g} μm", band_loss[:, b], "--") for b, w in enumerate(wavelengths))]
    curves_figure(iteration, [Panel(curves, "loss (Eq. 41)", log=True)], "iteration",
                  out / "loss.png")
    first, last = int(iteration[0]), int(iteration[-1])
    return ["## Loss", "", "![loss against iteration](loss.png)", "",
            f"| band [μm] | loss at iteration {first} | at iteration {last} |",
            "| --- | --- | --- |",
            *(f"| {w:g} | {band_loss[0, b]:.4g} | {band_loss[-1, b]:.4g} |"
              for b, w in enumerate(wavelengths)),
            f"| all | {loss[0]:.4g} | {loss[-1]:.4g} |", ""]


def _error_lines(result: xr.Dataset, truth: xr.Dataset, distance: np.ndarray | None,
                 out: Path) -> list[str]:
    """The section on the errors against the truth, with the log's error curves."""
    e = microphysics_errors(result, truth, distance)
    media = [("last iterate (lwc, reff)", e)]
    if "lwc_average" in result:
        averaging = json.loads(result.attrs.get("config", "{}")).get("averaging", "iterate")
        media.append((f"{averaging} average of the iterates (lwc_average, reff_average)",
                      microphysics_errors(result, truth, distance, of="_average")))

    def near(errors: dict[str, float], key: str, text: str) -> str:
        return "-" if distance is None else text.format(errors[f"{key}_near"])

    lines = [
        "## Error against the truth", "",
        f"r_eff's mean errors over the true cloud and (near) within optical distance "
        f"{NEAR:g} of its lit and viewed boundary:", "",
        "| medium | LWC epsilon (Eq. 54) | LWC delta (Eq. 54) | r_eff [μm] | r_eff relative "
        "| near: r_eff [μm] | near: r_eff relative |",
        "| --- | --- | --- | --- | --- | --- | --- |",
        *(f"| {name} | {x['lwc_epsilon']:.1%} | {x['lwc_delta']:+.1%} | "
          f"{x['reff_absolute_error']:.2f} | {x['reff_relative_error']:.1%} | "
          f"{near(x, 'reff_absolute_error', '{:.2f}')} | "
          f"{near(x, 'reff_relative_error', '{:.1%}')} |" for name, x in media), "",
        "The optical distance of a voxel: the true cloud's optical depth towards the sun plus "
        "that towards the nearest camera, in the shortest band (cloudct.mc.visibility; "
        "beyond it lies the veiled core, which the images barely see)."
        + ("" if distance is not None else " It needs the cameras and the sun: give "
           "--measurements."), ""]
    logged = [f"log_{key}" for key in e]
    if all(key in result for key in logged) and np.isfinite(
            result["log_lwc_epsilon"].values).any():
        iteration = result["iteration"].values

        def log(key: str) -> np.ndarray:
            return result[f"log_{key}"].values

        within = f"d < {NEAR:g}"
        curves_figure(iteration, [
            Panel([Curve("epsilon", log("lwc_epsilon")), Curve("delta", log("lwc_delta"))],
                  "LWC (Eq. 54)", zero=True),
            Panel([Curve("true cloud", log("reff_absolute_error")),
                   Curve(within, log("reff_absolute_error_near"), "--")],
                  "r_eff mean absolute error [μm]"),
            Panel([Curve("true cloud", log("reff_relative_error")),
                   Curve(within, log("reff_relative_error_near"), "--")],
                  "r_eff mean relative error"),
        ], "iteration", out / "errors.png")
        lines += ["The run's log (against the truth it was given):", "",
                  "![errors against iteration](errors.png)", ""]
    else:
        lines += ["The run's log holds no errors (it was retrieved without --truth).", ""]
    return lines


def _slice_lines(result: xr.Dataset, truth_fields: tuple[np.ndarray, np.ndarray] | None,
                 out: Path) -> list[str]:
    """The slices' section: LWC and r_eff (clear cells blank), the truth's above."""
    lwc, reff = (result[name].transpose(*GRID).values.astype(float) for name in ("lwc", "reff"))
    lwc_rows = [("retrieved", lwc)]
    reff_rows = [("retrieved", np.where(lwc > 0, reff, np.nan))]
    if truth_fields is not None:
        true_lwc, true_reff = truth_fields
        lwc_rows.insert(0, ("true", true_lwc))
        reff_rows.insert(0, ("true", np.where(true_lwc > 0, true_reff, np.nan)))
    z = result["z"].values
    slices_figure(lwc_rows, z, "LWC [g m-3]", out / "slices_lwc.png")
    slices_figure(reff_rows, z, "r_eff [μm]", out / "slices_reff.png", vmin=None)
    return ["## Slices", "", "![LWC slices](slices_lwc.png)", "",
            "![r_eff slices](slices_reff.png)", ""]


def _image_lines(result: xr.Dataset, bands: list[xr.Dataset], tables: list[xr.Dataset],
                 render_photons: int | None, backend: str, out: Path) -> list[str]:
    """The images' section: each band's measured images above the result's rendered with
    its Mie table, and their relative L1 difference."""
    wavelengths = [float(band.attrs["wavelength"]) for band in bands]
    optical = band_optics(_medium(result), wavelengths, mie_tables=tables, optics="mie")
    rows, figures, photons = [], [], []
    for w, band, medium in zip(wavelengths, bands, optical, strict=True):
        photons.append(render_photon_count(band, render_photons))
        images = render(medium, Scene.from_dataset(band), photons=photons[-1],
                        progress=False, backend=backend)
        backend = images.attrs["backend"]  # "auto" resolved
        measured, rendered = band["radiance"].values, images["radiance"].values
        name = f"images_{w:g}um.png"
        images_figure([("measured", measured), ("retrieved", rendered)], out / name,
                      title=f"{w:g} μm")
        rows.append(f"| {w:g} | {image_difference(measured, rendered):.1%} | {photons[-1]} |")
        figures += [f"![{w:g} μm]({name})", ""]
    return ["## Re-rendered vs measured images", "",
            f"Each band rendered from the result with its Mie table on the {backend} back end "
            "(their Monte Carlo noise is part of the difference):", "",
            "| band [μm] | relative L1 image difference | photons |", "| --- | --- | --- |",
            *rows, "", *figures]
