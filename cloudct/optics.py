"""From a medium Dataset to optical properties, and from those to the kernels' arrays.

:func:`to_optical` turns a microphysical medium (``lwc``, ``reff``) into an optical one
through a Mie table (:mod:`cloudct.physics.mie`):

- ``cloud_extinction = lwc * ext_per_lwc(reff)``, linear interpolation in r_eff;
- ``cloud_albedo``: the table's albedo, linear interpolation in r_eff;
- phase ``"mie"``: each cloudy cell's phase function linear in r_eff between the two table
  rows about its r_eff, (1 - t) row k + t row k + 1 (:mod:`cloudct.physics.microphysics`):
  ``cloud_phase`` holds the consecutive table rows the cloudy cells use (their r_eff in the
  coordinate ``cloud_phase_reff``), ``cloud_phase_index`` each cell's row k and
  ``cloud_phase_weight`` its t; phase ``"hg"``: ``cloud_g`` = g;
- ``air_extinction``: scaled from the wavelength the medium gives it at
  (:func:`air_wavelength`) to the optics' wavelength as Rayleigh scattering
  (:func:`cloudct.physics.air.air_extinction_at`, Bodhaine et al. 1999, Eq. 30).

:func:`band_optics` gives one optical medium per band (wavelength) of a microphysical one.

:func:`kernel_arrays` builds the :class:`OpticalGrid` and :class:`PhaseBank` of the numba
kernels: type 0 air (Rayleigh, bank row 0), type 1 cloud (one bank row per distinct HG g,
or one per tabulated phase function, with each cell's weight of the next row).

A medium with tabulated (Mie) phase functions may carry the attribute ``phase_truncation``
(degrees, :func:`with_phase_truncation`): the kernels then see each phase function's
forward peak cut flat at that angle and the cloud's extinction and albedo delta-scaled
(:func:`cloudct.physics.phase.truncated_peak`), so that every estimator traces the
truncated optics, while the medium, and every gradient, stays in the true cloud
extinction beta (:func:`cloud_extinction_scale`: the chain rule d beta' / d beta).
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from cloudct.medium import (
    AIR_EXTINCTION_WAVELENGTH,
    DEFAULT_CLOUD_ALBEDO,
    DEFAULT_CLOUD_G,
    DEFAULT_VEFF,
    cell_edges,
    is_microphysical,
    is_optical,
    optical_medium,
    validate_medium,
)
from cloudct.physics.air import air_extinction_at
from cloudct.physics.microphysics import reff_interval
from cloudct.physics.mie import DEFAULT_WAVELENGTH
from cloudct.physics.mie import mie_table as load_mie_table
from cloudct.physics.mixing import OpticalGrid
from cloudct.physics.phase import PhaseBank, phase_bank, truncated_peak
from cloudct.physics.transmittance import EXPONENTIAL, GAMMA
from cloudct.physics.transmittance import FAMILIES as TRANSMITTANCE_FAMILIES

GRID = ("x", "y", "z")
#: The attribute of a medium with tabulated phase functions that cuts their forward peak
#: flat at that many degrees for the kernels (:func:`with_phase_truncation`).
PHASE_TRUNCATION = "phase_truncation"

#: The cloud optics a microphysical medium can be given (:func:`to_optical`).
OPTICS = ("hg", "mie")
#: The documented default: the seed paper's optics, with which every retrieval in
#: docs/benchmarks.md was measured. ``"mie"`` is the physically exact choice; its peaked
#: phase functions make the gradient much noisier per photon (docs/benchmarks.md, "Mie
#: optics").
DEFAULT_OPTICS = "hg"


def optics_choice(medium: xr.Dataset, optics: str | None = None) -> str:
    """The cloud optics to give ``medium``: ``optics`` when given, else the choice recorded
    in its ``optics`` attribute, else :data:`DEFAULT_OPTICS`."""
    choice = optics if optics is not None else medium.attrs.get("optics", DEFAULT_OPTICS)
    if choice not in OPTICS:
        where = "optics" if optics is not None else "the medium's optics attribute"
        raise ValueError(f"{where} must be one of {OPTICS}, got {choice!r}")
    return choice


def with_optics(medium: xr.Dataset, optics: str | None) -> xr.Dataset:
    """``medium`` with the cloud optics ``optics`` chosen (None: as it is). A microphysical
    medium records the choice in its ``optics`` attribute and is converted where it is used
    (at that use's wavelength); an optical medium already has its optics, and a different
    choice is an error."""
    if optics is None:
        return medium
    if is_optical(medium):
        return to_optical(medium, optics=optics)  # refuses a different choice
    return medium.assign_attrs(optics=optics_choice(medium, optics))


def optics_name(medium: xr.Dataset) -> str:
    """The name of the cloud optics ``medium`` has or will be given, for the attributes of
    the files made from it: its recorded ``optics`` if optical (``"unrecorded"`` where a
    medium built by hand records none), else :func:`optics_choice`."""
    if is_optical(medium):
        return str(medium.attrs.get("optics", "unrecorded"))
    return optics_choice(medium)


def air_wavelength(medium: xr.Dataset) -> float:
    """The wavelength [micron] at which ``medium``'s ``air_extinction`` is given: its
    attribute ``air_extinction_wavelength``, else 0.672 (:data:`DEFAULT_WAVELENGTH`, where the
    seed paper's 0.04 km-1 is given)."""
    return float(medium.attrs.get(AIR_EXTINCTION_WAVELENGTH, DEFAULT_WAVELENGTH))


def _single_veff(medium: xr.Dataset) -> float:
    """The droplet effective variance of the cloud, which must be one value for a table."""
    if "veff" not in medium:
        return DEFAULT_VEFF
    veff = medium["veff"].broadcast_like(medium["lwc"]).values[medium["lwc"].values > 0]
    values = np.unique(veff)
    if values.size > 1:
        raise ValueError(
            f"veff varies over the cloud ({values.min():g}..{values.max():g}); "
            "the Mie optics use one table, i.e. one veff"
        )
    return float(values[0]) if values.size else DEFAULT_VEFF


def to_optical(
    medium: xr.Dataset,
    mie_table: xr.Dataset | None = None,
    *,
    wavelength: float | None = None,
    optics: str | None = None,
) -> xr.Dataset:
    """Optical medium (cloud extinction, albedo, phase function) from a microphysical one.

    Args:
        medium: a medium Dataset with ``lwc`` [g m-3] and ``reff`` [micron]. A medium that
            is already optical is returned unchanged (an ``optics`` that differs from the
            one it records is an error).
        mie_table: a table from :func:`cloudct.physics.mie.mie_table`; by default the table
            for ``wavelength`` and the medium's ``veff`` (default 0.1).
        wavelength: [micron]; default 0.672, or the table's when ``mie_table`` is given
            (a different value is an error).
        optics: one of :data:`OPTICS` (None: :func:`optics_choice`). ``"mie"``: the table's
            albedo and tabulated Mie phase functions (linear in r_eff between table rows);
            ``"hg"``: the seed paper's optics, Henyey-Greenstein with g =
            :data:`DEFAULT_CLOUD_G` and cloud albedo :data:`DEFAULT_CLOUD_ALBEDO`. The extinction is
            the table's for both.

    Returns:
        A validated optical medium on the same grid, keeping the microphysics and the
        attributes, with the ``wavelength`` attribute set, ``optics`` set to the choice
        and ``optics_description`` saying what it is. The air keeps its albedo; its
        extinction is scaled from :func:`air_wavelength` to the wavelength as Rayleigh
        scattering (:func:`cloudct.physics.air.air_extinction_at`; unchanged at the same
        wavelength), and the attribute ``air_extinction_wavelength`` says the wavelength.

    Raises:
        ValueError: r_eff outside the table's range where lwc > 0, an unknown ``optics``,
            or a wavelength or veff that differs from the given table's.
    """
    if is_optical(medium):
        recorded = medium.attrs.get("optics")
        if optics is not None and recorded is not None and optics != recorded:
            raise ValueError(f"the medium is already optical with optics {recorded!r}; "
                             f"{optics!r} applies to a microphysical medium (lwc, reff)")
        return medium
    if not is_microphysical(medium):
        raise ValueError("medium has neither lwc + reff nor an optical cloud description")
    phase = optics_choice(medium, optics)
    validate_medium(medium)
    veff = _single_veff(medium)
    if mie_table is None:
        mie_table = load_mie_table(
            wavelength=DEFAULT_WAVELENGTH if wavelength is None else wavelength, veff=veff
        )
    table_wavelength = float(mie_table.attrs["wavelength"])
    if wavelength is not None and not np.isclose(wavelength, table_wavelength):
        raise ValueError(f"wavelength {wavelength} differs from the table's {table_wavelength}")
    if not np.isclose(veff, float(mie_table.attrs["veff"])):
        raise ValueError(f"medium veff {veff} differs from the table's {mie_table.attrs['veff']}")

    lwc = medium["lwc"].transpose(*GRID).values
    reff = medium["reff"].transpose(*GRID).values
    table_reff = mie_table["reff"].values
    cloudy = lwc > 0
    outside = cloudy & ((reff < table_reff[0]) | (reff > table_reff[-1]))
    if np.any(outside):
        raise ValueError(
            f"{int(outside.sum())} cloudy cells have reff outside the Mie table's range "
            f"{table_reff[0]:g}..{table_reff[-1]:g} micron (found "
            f"{reff[outside].min():g}..{reff[outside].max():g})"
        )
    # clear cells (lwc = 0) get the optics at the clipped r_eff: their extinction is 0
    r = np.clip(reff, table_reff[0], table_reff[-1])
    extinction = lwc * np.interp(r, table_reff, mie_table["ext_per_lwc"].values)
    albedo = np.interp(r, table_reff, mie_table["albedo"].values)

    if phase == "hg":
        albedo = np.full(lwc.shape, DEFAULT_CLOUD_ALBEDO)
        phase_args = {"cloud_g": DEFAULT_CLOUD_G}
        description = (f"Henyey-Greenstein phase function, g = {DEFAULT_CLOUD_G:g}, cloud albedo "
                       f"{DEFAULT_CLOUD_ALBEDO:g}")
    else:
        lower, weight = reff_interval(r, mie_table)
        # the rows of every cloudy cell's interval (row k + 1 even where t = 0: the
        # derivative in r_eff there is the interval's)
        first = int(lower[cloudy].min()) if cloudy.any() else 0
        rows = np.arange(first, int(lower[cloudy].max()) + 2 if cloudy.any() else 1)
        phase_args = {
            "cloud_phase": (mie_table["phase"].values[rows], mie_table["scattering_angle"].values),
            "cloud_phase_index": np.where(cloudy, lower - first, 0).astype(np.int32),
            "cloud_phase_weight": np.where(cloudy, weight, 0.0),
        }
        description = "Mie albedo and phase functions linear in reff between table rows"

    air = medium["air_extinction"]
    air = air.copy(data=air_extinction_at(air.values, table_wavelength, air_wavelength(medium)))
    optical = optical_medium(
        medium["x"].values,
        medium["y"].values,
        medium["z"].values,
        extinction,
        cloud_albedo=albedo,
        air_extinction=air,
        air_albedo=float(medium["air_albedo"]),
        z_bounds=medium["z_bounds"].values if "z_bounds" in medium else None,
        wavelength=table_wavelength,
        **phase_args,
    )
    if phase == "mie":
        optical = optical.assign_coords(
            cloud_phase_reff=(
                "phase_table",
                table_reff[rows],
                {"units": "micron", "long_name": "effective radius of each phase table row"},
            )
        )
    for name in ("lwc", "reff", "veff"):
        if name in medium:
            optical[name] = medium[name]
    optical.attrs = {
        **medium.attrs,
        "Conventions": "CF-1.8",
        "wavelength": table_wavelength,
        AIR_EXTINCTION_WAVELENGTH: table_wavelength,
        AIR_EXTINCTION_WAVELENGTH + "_units": "micron",
        "optics": phase,
        "optics_description": f"extinction from the Mie table "
        f"({mie_table.attrs.get('mie_code', 'unknown code')}), veff = {veff:g}; {description}",
    }
    validate_medium(optical)
    return optical


def band_optics(
    medium: xr.Dataset,
    wavelengths,
    *,
    mie_tables=None,
    optics: str | None = None,
) -> list[xr.Dataset]:
    """One optical medium per band: :func:`to_optical` of the microphysical ``medium`` at
    each of ``wavelengths`` [micron], the air scaled to each.

    Args:
        medium: a microphysical medium (``lwc``, ``reff``).
        wavelengths: the bands' wavelengths [micron].
        mie_tables: one Mie table per band, at its wavelength; None: the default table of
            each wavelength (:func:`cloudct.physics.mie.mie_table`, with the refractive
            index of water of :mod:`cloudct.physics.water`; computed and cached once).
        optics: as in :func:`to_optical`. With ``"hg"`` every band has the seed paper's
            cloud albedo and g (only the extinction and the air change with the band);
            ``"mie"`` gives each band its droplets' absorption and phase functions.

    Raises:
        ValueError: an optical ``medium`` (its optics are one wavelength's), a number of
            tables that is not the number of bands, or what :func:`to_optical` raises.
    """
    if is_optical(medium) or not is_microphysical(medium):
        raise ValueError("band optics need a microphysical medium (lwc, reff)")
    wavelengths = [float(w) for w in wavelengths]
    tables = [None] * len(wavelengths) if mie_tables is None else list(mie_tables)
    if len(tables) != len(wavelengths):
        raise ValueError(f"{len(tables)} Mie tables for {len(wavelengths)} bands")
    return [to_optical(medium, table, wavelength=w, optics=optics)
            for w, table in zip(wavelengths, tables, strict=True)]


def _on_grid(da: xr.DataArray, template: xr.DataArray) -> np.ndarray:
    """A scalar, z-profile or 3D variable broadcast to (x, y, z)."""
    return da.broadcast_like(template).transpose(*GRID).values


def phase_truncation(medium: xr.Dataset) -> float:
    """The medium's ``phase_truncation`` attribute in degrees (0: none), checked: a number
    in [0, 90), and above 0 only with tabulated cloud phase functions."""
    value = medium.attrs.get(PHASE_TRUNCATION, 0.0)
    try:
        degrees = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"phase_truncation must be a number of degrees, got {value!r}") from None
    if not 0.0 <= degrees < 90.0:
        raise ValueError(f"phase_truncation must be in [0, 90) degrees, got {degrees}")
    if degrees > 0.0 and "cloud_phase" not in medium:
        raise ValueError("phase_truncation applies to tabulated (Mie) cloud phase functions; "
                         "this medium's cloud has none (Henyey-Greenstein has no peak to cut)")
    return degrees


def with_phase_truncation(medium: xr.Dataset, degrees: float) -> xr.Dataset:
    """``medium`` (optical, or microphysical: converted by :func:`to_optical` first) with
    its ``phase_truncation`` attribute set to ``degrees`` (0 removes it): the kernels trace
    its phase functions cut flat at that angle (module documentation)."""
    optical = medium if is_optical(medium) else to_optical(medium)
    out = optical.copy()
    out.attrs = {k: v for k, v in optical.attrs.items()
                 if k not in (PHASE_TRUNCATION, PHASE_TRUNCATION + "_units")}
    if degrees:
        out.attrs[PHASE_TRUNCATION] = float(degrees)
        out.attrs[PHASE_TRUNCATION + "_units"] = "degree"
    phase_truncation(out)
    return out


def _peak_fractions(ds: xr.Dataset, truncation: float) -> tuple[list[tuple], np.ndarray | None]:
    """The tabulated bank entries of the cloud's phase functions and, with a truncation
    (degrees, > 0), the share f of scattering each one's cut removes (None without)."""
    angles = ds["scattering_angle"].values
    if truncation == 0.0:
        return [("tabulated", angles, row) for row in ds["cloud_phase"].values], None
    cut = [truncated_peak(angles, row, truncation) for row in ds["cloud_phase"].values]
    return [("tabulated", a, v) for a, v, _ in cut], np.array([f for _, _, f in cut])


def _delta_scaled(ds: xr.Dataset, cloud: xr.DataArray, fractions: np.ndarray | None,
                  weight: np.ndarray):
    """The cloud's extinction, albedo and next-row weight as the kernels see them, and
    d beta' / d beta (None without a truncation): beta' = beta (1 - omega f), omega' =
    omega (1 - f) / (1 - omega f), f the truncated share of each voxel's phase function.
    A cell's mixture (1 - t) p_k + t p_{k+1}, rows that lose f_k and f_{k+1}, loses f =
    (1 - t) f_k + t f_{k+1}, and its truncated rows mix with t' = t (1 - f_{k+1}) / (1 - f)."""
    albedo = _on_grid(ds["cloud_albedo"], cloud)
    if fractions is None:
        return cloud.values, albedo, weight, None
    f_row, f_next = _cell_shares(ds, fractions)
    f = (1.0 - weight) * f_row + weight * f_next
    scale = 1.0 - albedo * f
    weight = np.where(weight > 0.0, weight * (1.0 - f_next) / (1.0 - f), 0.0)
    return cloud.values * scale, albedo * (1.0 - f) / scale, weight, scale


def _cell_shares(ds: xr.Dataset, fractions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The cut shares f_k and f_{k+1} of each cell's two phase-function rows, over (x, y, z)."""
    k = ds["cloud_phase_index"].transpose(*GRID).values
    return fractions[k], fractions[np.minimum(k + 1, fractions.size - 1)]


def peak_shares(optical_medium: xr.Dataset) -> tuple[np.ndarray, np.ndarray] | None:
    """The shares f_k and f_{k+1} of scattering that the phase truncation cuts from each
    cell's two tabulated rows (:func:`cloudct.physics.phase.truncated_peak`), float64[x, y,
    z] each; None where the medium has no phase truncation."""
    truncation = phase_truncation(optical_medium)
    if truncation == 0.0:
        return None
    return _cell_shares(optical_medium, _peak_fractions(optical_medium, truncation)[1])


def cloud_extinction_scale(optical_medium: xr.Dataset) -> np.ndarray | None:
    """d beta' / d beta per voxel, float64[x, y, z]: the factor between a gradient with
    respect to the kernels' (delta-scaled) cloud extinction and one with respect to the
    medium's; None where the medium has no phase truncation (the factor is 1). The third
    item of :func:`kernel_arrays_and_scale`, which estimators take with the arrays."""
    return kernel_arrays_and_scale(optical_medium)[2]


def kernel_arrays(optical_medium: xr.Dataset) -> tuple[OpticalGrid, PhaseBank]:
    """The numba kernels' view of an optical medium: ``(grid, bank)`` of
    :func:`kernel_arrays_and_scale`."""
    return kernel_arrays_and_scale(optical_medium)[:2]


def kernel_arrays_and_scale(
    optical_medium: xr.Dataset,
) -> tuple[OpticalGrid, PhaseBank, np.ndarray | None]:
    """The numba kernels' view of an optical medium, and the chain-rule factor of its phase
    truncation (:func:`cloud_extinction_scale`), the cut computed once.

    Args:
        optical_medium: a medium with an optical cloud description (see :func:`to_optical`).

    Returns:
        ``(grid, bank, scale)``. Type 0 is air: ``air_extinction`` broadcast to 3D, ``air_albedo``,
        bank row 0 (Rayleigh). Type 1 is cloud: ``cloud_extinction``, ``cloud_albedo`` and
        either one HG bank row per distinct ``cloud_g`` value or one tabulated row per row
        of ``cloud_phase`` (bank row 1 + ``cloud_phase_index``, with the weight
        ``cloud_phase_weight`` of the next row), cut and delta-scaled where
        the medium has a ``phase_truncation`` (module documentation). Arrays are
        C-contiguous float64 (int32 phase indices). ``scale``: d beta' / d beta per voxel,
        None without a truncation.

    Raises:
        ValueError: the medium has no optical cloud description.
    """
    ds = optical_medium
    if not is_optical(ds):
        raise ValueError("kernel_arrays needs an optical medium: convert it with to_optical")
    validate_medium(ds)
    x_edges, y_edges, z_edges = cell_edges(ds)
    cloud = ds["cloud_extinction"].transpose(*GRID)
    shape = cloud.shape

    entries: list[tuple] = [("rayleigh",)]
    phase_index = np.zeros((2, *shape), dtype=np.int32)
    phase_weight = np.zeros((2, *shape))
    fractions = None
    truncation = phase_truncation(ds)  # checked for HG media too
    if "cloud_phase" in ds:
        tabulated, fractions = _peak_fractions(ds, truncation)
        entries += tabulated
        phase_index[1] = 1 + ds["cloud_phase_index"].transpose(*GRID).values
        if "cloud_phase_weight" in ds:
            phase_weight[1] = ds["cloud_phase_weight"].transpose(*GRID).values
    else:
        gs, inverse = np.unique(_on_grid(ds["cloud_g"], cloud), return_inverse=True)
        entries += [("hg", gv) for gv in gs]
        phase_index[1] = 1 + inverse.reshape(shape)

    cloud_extinction, cloud_albedo, phase_weight[1], scale = _delta_scaled(
        ds, cloud, fractions, phase_weight[1])
    extinction = np.stack([_on_grid(ds["air_extinction"], cloud), cloud_extinction])
    albedo = np.stack([_on_grid(ds["air_albedo"], cloud), cloud_albedo])
    grid = OpticalGrid(
        x_edges=np.ascontiguousarray(x_edges, dtype=np.float64),
        y_edges=np.ascontiguousarray(y_edges, dtype=np.float64),
        z_edges=np.ascontiguousarray(z_edges, dtype=np.float64),
        extinction=np.ascontiguousarray(extinction, dtype=np.float64),
        albedo=np.ascontiguousarray(albedo, dtype=np.float64),
        phase_index=np.ascontiguousarray(phase_index),
        phase_weight=np.ascontiguousarray(phase_weight),
        cloud_reff_slopes=np.zeros((2, 1, 1, 1)),
        **_transmittance_arrays(ds, cloud),
    )
    return grid, phase_bank(entries), scale


def _transmittance_arrays(ds: xr.Dataset, cloud: xr.DataArray) -> dict[str, np.ndarray]:
    """The kernels' transmittance family code and mode per voxel
    (:mod:`cloudct.physics.transmittance`): gamma of Eq. 6 for ``linear-mix``, 1 / a for
    ``gamma`` (0 where a = inf: exponential)."""
    family = TRANSMITTANCE_FAMILIES[ds.attrs.get("transmittance", "exponential")]
    mode = np.zeros((1, 1, 1))
    if family != EXPONENTIAL:
        mode = _on_grid(ds["transmittance_mode"], cloud).astype(np.float64)
        if family == GAMMA:
            mode = 1.0 / mode
    return {"transmittance_family": np.array([family], dtype=np.int64),
            "transmittance_mode": np.ascontiguousarray(mode)}
