"""The medium Dataset: constructors, validation, cell edges and netCDF round trips."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from cloudct.medium import (
    MediumError,
    cell_edges,
    domain_bounds,
    is_microphysical,
    is_optical,
    load_medium,
    microphysical_medium,
    optical_medium,
    save_medium,
    validate_medium,
)

NX, NY, NZ = 3, 4, 5
X = 0.01 + 0.02 * np.arange(NX)
Y = 0.01 + 0.02 * np.arange(NY)
Z = 0.52 + 0.04 * np.arange(NZ)
# Non-uniform layers for the bounds tests: thicknesses 0.02, 0.04, 0.04, 0.06, 0.08 km.
Z_EDGES = np.array([0.5, 0.52, 0.56, 0.6, 0.66, 0.74])
Z_BOUNDS = np.stack([Z_EDGES[:-1], Z_EDGES[1:]], axis=1)
ANGLES = np.linspace(0.0, 180.0, 7)


def _lwc() -> np.ndarray:
    lwc = np.zeros((NX, NY, NZ))
    lwc[1, 1:3, 1:4] = [[0.1, 0.4, 0.2], [0.3, 0.8, 0.5]]
    return lwc


def micro() -> xr.Dataset:
    lwc = _lwc()
    return microphysical_medium(X, Y, Z, lwc, np.where(lwc > 0, 10.0, 0.0), veff=0.1)


def optical() -> xr.Dataset:
    return optical_medium(X, Y, Z, 1500 * _lwc() / 10.0, cloud_g=0.85)


def tabulated() -> xr.Dataset:
    table = np.array([np.full(ANGLES.size, 1 / (4 * np.pi)), np.linspace(0.2, 0.02, ANGLES.size)])
    index = np.zeros((NX, NY, NZ), dtype=int)
    index[1] = 1
    return optical_medium(
        X, Y, Z, 1500 * _lwc() / 10.0, cloud_phase=(table, ANGLES), cloud_phase_index=index
    )


# ---------------------------------------------------------------------------------------
# Constructors and queries
# ---------------------------------------------------------------------------------------


def test_microphysical_constructor_schema():
    ds = micro()
    assert is_microphysical(ds) and not is_optical(ds)
    assert ds["lwc"].dims == ("x", "y", "z")
    assert ds.attrs["Conventions"] == "CF-1.8"
    assert ds["air_extinction"].item() == 0.04 and ds["air_albedo"].item() == 0.912
    for name in ds.variables:
        if name != "nv":
            assert {"units", "long_name"} <= set(ds[name].attrs), name
    assert ds["lwc"].attrs["units"] == "g m-3"
    assert ds["reff"].attrs["units"] == "micron"
    assert ds["x"].attrs["units"] == "km"


def test_optical_constructor_defaults_and_units():
    ds = optical()
    assert is_optical(ds) and not is_microphysical(ds)
    assert ds["cloud_albedo"].item() == 0.99
    assert ds["cloud_g"].item() == 0.85
    assert ds["cloud_extinction"].attrs["units"] == "km-1"
    assert ds["air_extinction"].attrs["units"] == "km-1"


def test_tabulated_phase_constructor():
    ds = tabulated()
    assert is_optical(ds) and "cloud_g" not in ds
    assert ds["cloud_phase"].dims == ("phase_table", "scattering_angle")
    assert ds["cloud_phase"].attrs["units"] == "sr-1"
    assert ds["scattering_angle"].attrs["units"] == "degree"
    assert ds["cloud_phase_index"].dtype == np.int32


def test_single_row_phase_table_needs_no_index():
    ds = optical_medium(X, Y, Z, _lwc(), cloud_phase=(np.ones(ANGLES.size), ANGLES))
    assert ds["cloud_phase"].shape == (1, ANGLES.size)
    assert np.all(ds["cloud_phase_index"].values == 0)


@pytest.mark.parametrize(
    "air, dims",
    [
        (0.03, ()),
        (np.linspace(0.05, 0.03, NZ), ("z",)),
        (np.full((NX, NY, NZ), 0.02), ("x", "y", "z")),
    ],
    ids=["scalar", "profile", "field"],
)
def test_air_extinction_forms(air, dims):
    ds = optical_medium(X, Y, Z, _lwc(), air_extinction=air)
    assert ds["air_extinction"].dims == dims
    np.testing.assert_array_equal(ds["air_extinction"].values, air)


def test_air_extinction_dataarray_on_the_grid_is_accepted():
    air = xr.DataArray(np.full((NZ, NY, NX), 0.02), dims=("z", "y", "x"), coords={"z": Z})
    ds = optical_medium(X, Y, Z, _lwc(), air_extinction=air)
    assert ds["air_extinction"].dims == ("x", "y", "z")


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"air_extinction": np.full((NX, NY, NZ + 1), 0.04)}, "air_extinction"),
        ({"air_extinction": np.full(NX, 0.04)}, "air_extinction"),
        ({"cloud_albedo": np.full((NX, NY), 0.9)}, "cloud_albedo"),
        ({"cloud_g": 0.8, "cloud_phase": (np.ones(7), ANGLES)}, "cloud_g"),
        ({"cloud_phase": (np.ones((2, 7)), ANGLES)}, "cloud_phase_index"),
        ({"cloud_phase": (np.ones((1, 6)), ANGLES)}, "cloud_phase"),
        ({"cloud_phase": (np.ones((2, 7)), ANGLES), "cloud_phase_index": 2}, "cloud_phase_index"),
        (
            {"cloud_phase": (np.ones((2, 7)), ANGLES), "cloud_phase_index": np.zeros((NX, NY, NZ))},
            "cloud_phase_index",
        ),
        ({"cloud_phase_index": 0}, "cloud_phase_index"),
        ({"z_bounds": Z_BOUNDS[:-1]}, "z_bounds"),
    ],
)
def test_optical_constructor_rejects(kwargs, name):
    with pytest.raises(MediumError, match=name):
        optical_medium(X, Y, Z, _lwc(), **kwargs)


def test_constructor_rejects_air_on_other_coordinates():
    shifted = xr.DataArray(
        np.full((NX, NY, NZ), 0.04), dims=("x", "y", "z"), coords={"x": X + 0.005, "y": Y, "z": Z}
    )
    with pytest.raises(MediumError, match="air_extinction is on other x coordinates"):
        optical_medium(X, Y, Z, _lwc(), air_extinction=shifted)


def test_constructor_rejects_wrong_lwc_shape():
    with pytest.raises(MediumError, match="lwc has shape"):
        microphysical_medium(X, Y, Z, np.zeros((NZ, NY, NX)), np.zeros((NZ, NY, NX)))


def test_reff_is_free_where_there_is_no_water():
    """reff may be 0 (or any value >= 0) in clear cells; only cloudy cells need reff > 0."""
    lwc = _lwc()
    reff = np.where(lwc > 0, 12.0, 0.0)
    reff[0, 0, 0] = 4.0
    ds = microphysical_medium(X, Y, Z, lwc, reff)
    assert ds["reff"].values[0, 0, 0] == 4.0


def test_cell_edges_uniform():
    x_edges, y_edges, z_edges = cell_edges(micro())
    np.testing.assert_allclose(x_edges, 0.02 * np.arange(NX + 1), atol=1e-12)
    np.testing.assert_allclose(y_edges, 0.02 * np.arange(NY + 1), atol=1e-12)
    np.testing.assert_allclose(z_edges, 0.5 + 0.04 * np.arange(NZ + 1), atol=1e-12)
    assert all(e.dtype == np.float64 for e in (x_edges, y_edges, z_edges))


def test_cell_edges_and_bounds_with_z_bounds():
    z = Z_BOUNDS.mean(axis=1)
    ds = optical_medium(X, Y, z, _lwc(), z_bounds=Z_BOUNDS)
    assert ds["z"].attrs["bounds"] == "z_bounds"
    np.testing.assert_array_equal(cell_edges(ds)[2], Z_EDGES)
    bounds = domain_bounds(ds)
    assert bounds.z_min == 0.5 and bounds.z_max == 0.74
    assert bounds.x_min == pytest.approx(0.0) and bounds.x_max == pytest.approx(0.06)
    assert bounds.y_max == pytest.approx(0.08)


# ---------------------------------------------------------------------------------------
# Validation: one case per rule; the message must name the offending variable.
# ---------------------------------------------------------------------------------------


def _set(name, value):
    return lambda ds: ds.assign({name: value})


def _set_attr(name, key, value):
    def mutate(ds):
        ds = ds.copy()
        ds[name].attrs[key] = value
        return ds

    return mutate


def _put(name, index, value):
    def mutate(ds):
        ds = ds.copy(deep=True)
        ds[name].values[index] = value
        return ds

    return mutate


def _coordinate(name, values):
    return lambda ds: ds.assign_coords({name: (name, values, ds[name].attrs)})


def _non_uniform_z_with_bounds(ds):
    return ds.assign_coords(z=("z", Z_BOUNDS.mean(axis=1), {**ds["z"].attrs, "bounds": "z_bounds"}))


def _with_bounds(bounds):
    def mutate(ds):
        ds = _non_uniform_z_with_bounds(ds)
        return ds.assign(z_bounds=(("z", "nv"), bounds, {"units": "km"}))

    return mutate


def _shifted_air(ds):
    air = xr.DataArray(
        np.full((NX, NY, NZ), 0.04), dims=("x", "y", "z"), coords={"x": X + 0.02, "y": Y, "z": Z}
    )
    ds = ds.copy()
    ds["air_extinction"] = air  # xarray aligns on x: the cells outside the overlap get NaN
    return ds


_bad_contiguity = Z_BOUNDS.copy()
_bad_contiguity[2, 0] += 0.005


def _z_off_centre(ds):
    ds = _with_bounds(Z_BOUNDS)(ds)
    z = ds["z"].values.copy()
    z[2] += 0.005
    return ds.assign_coords(z=("z", z, ds["z"].attrs))


VALIDATION_CASES = [
    # missing or partial descriptions
    ("no cloud", micro, lambda ds: ds.drop_vars(["lwc", "reff", "veff"]), "lwc", "no cloud"),
    ("no reff", micro, lambda ds: ds.drop_vars("reff"), "reff", "is missing"),
    ("veff alone", optical, _set("veff", 0.1), "lwc", "incomplete microphysical"),
    ("no albedo", optical, lambda ds: ds.drop_vars("cloud_albedo"), "cloud_albedo", "missing"),
    ("no phase", optical, lambda ds: ds.drop_vars("cloud_g"), "cloud_g", "no phase function"),
    ("no index", tabulated, lambda ds: ds.drop_vars("cloud_phase_index"), "cloud_phase_index", ""),
    ("g and table", tabulated, _set("cloud_g", 0.8), "cloud_g", "keep one"),
    ("no air", micro, lambda ds: ds.drop_vars("air_extinction"), "air_extinction", "missing"),
    ("no air albedo", micro, lambda ds: ds.drop_vars("air_albedo"), "air_albedo", "missing"),
    ("no x", micro, lambda ds: ds.drop_vars("x"), "x", "coordinate x is missing"),
    # dimensions
    (
        "transposed lwc",
        micro,
        lambda ds: ds.assign(lwc=ds["lwc"].transpose("z", "y", "x")),
        "lwc",
        "dimensions",
    ),
    ("air on y", micro, _set("air_extinction", ("y", np.full(NY, 0.04))), "air_extinction", "dim"),
    (
        "3D air albedo",
        micro,
        _set("air_albedo", (("x", "y", "z"), np.full((NX, NY, NZ), 0.9))),
        "air_albedo",
        "dimensions",
    ),
    # non-finite values
    (
        "NaN extinction",
        optical,
        _put("cloud_extinction", (0, 0, 0), np.nan),
        "cloud_extinction",
        "NaN",
    ),
    ("inf reff", micro, _put("reff", (1, 1, 1), np.inf), "reff", "infinite"),
    ("NaN phase", tabulated, _put("cloud_phase", (1, 2), np.nan), "cloud_phase", "NaN"),
    ("air on other grid", micro, _shifted_air, "air_extinction", "other coordinates"),
    # signs and ranges
    ("negative lwc", micro, _put("lwc", (0, 0, 0), -0.1), "lwc", ">= 0"),
    ("negative reff", micro, _put("reff", (0, 0, 0), -1.0), "reff", ">= 0"),
    ("cloudy reff 0", micro, _put("reff", (1, 1, 1), 0.0), "reff", "where lwc > 0"),
    ("veff 0", micro, _set("veff", 0.0), "veff", "where lwc > 0"),
    (
        "negative extinction",
        optical,
        _put("cloud_extinction", (2, 3, 4), -1.0),
        "cloud_extinction",
        ">= 0",
    ),
    (
        "negative air",
        micro,
        _set("air_extinction", ("z", np.full(NZ, -0.01))),
        "air_extinction",
        ">= 0",
    ),
    ("albedo > 1", optical, _set("cloud_albedo", 1.2), "cloud_albedo", "[0, 1]"),
    ("air albedo < 0", optical, _set("air_albedo", -0.1), "air_albedo", "[0, 1]"),
    ("g = 1", optical, _set("cloud_g", 1.0), "cloud_g", "-1 < g < 1"),
    (
        "g field -1",
        optical,
        _set("cloud_g", (("x", "y", "z"), np.full((NX, NY, NZ), -1.0))),
        "cloud_g",
        "-1 < g < 1",
    ),
    # coordinates and bounds
    ("x reversed", micro, _coordinate("x", X[::-1]), "x", "strictly increasing"),
    (
        "y repeated",
        micro,
        _coordinate("y", np.array([0.01, 0.03, 0.03, 0.05])),
        "y",
        "strictly increasing",
    ),
    ("x uneven", micro, _coordinate("x", np.array([0.01, 0.03, 0.06])), "x", "uniformly"),
    ("z uneven", micro, _coordinate("z", Z_BOUNDS.mean(axis=1)), "z", "z_bounds"),
    ("bounds not contiguous", micro, _with_bounds(_bad_contiguity), "z_bounds", "contiguous"),
    ("bounds vs z", micro, _z_off_centre, "z_bounds", "midpoint"),
    (
        "bounds without attr",
        micro,
        lambda ds: ds.assign(z_bounds=(("z", "nv"), np.stack([Z - 0.02, Z + 0.02], axis=1))),
        "z",
        "bounds",
    ),
    ("attr without bounds", micro, _set_attr("z", "bounds", "z_bounds"), "z_bounds", "no z_bounds"),
    # tabulated phase functions
    ("negative phase row", tabulated, _put("cloud_phase", (1, 3), -0.01), "cloud_phase", "row 1"),
    (
        "zero phase row",
        tabulated,
        _set("cloud_phase", (("phase_table", "scattering_angle"), np.zeros((2, ANGLES.size)))),
        "cloud_phase",
        "zero",
    ),
    (
        "angles to 170",
        tabulated,
        _coordinate("scattering_angle", np.linspace(0, 170, 7)),
        "scattering_angle",
        "0 to 180",
    ),
    (
        "index too large",
        tabulated,
        _put("cloud_phase_index", (0, 0, 0), 2),
        "cloud_phase_index",
        "outside 0..1",
    ),
    (
        "index negative",
        tabulated,
        _put("cloud_phase_index", (0, 0, 0), -1),
        "cloud_phase_index",
        "outside",
    ),
    (
        "float index",
        tabulated,
        lambda ds: ds.assign(cloud_phase_index=ds["cloud_phase_index"] * 1.0),
        "cloud_phase_index",
        "integer",
    ),
    # units
    (
        "extinction in m-1",
        optical,
        _set_attr("cloud_extinction", "units", "m-1"),
        "cloud_extinction",
        "'km-1'",
    ),
    ("lwc in kg m-3", micro, _set_attr("lwc", "units", "kg m-3"), "lwc", "'g m-3'"),
    ("reff in m", micro, _set_attr("reff", "units", "m"), "reff", "'micron'"),
    ("x in m", micro, _set_attr("x", "units", "m"), "x", "'km'"),
    (
        "angles in rad",
        tabulated,
        _set_attr("scattering_angle", "units", "rad"),
        "scattering_angle",
        "'degree'",
    ),
    # attributes
    (
        "negative wavelength",
        optical,
        lambda ds: ds.assign_attrs(wavelength=-0.672),
        "wavelength",
        "> 0",
    ),
]


@pytest.mark.parametrize(
    "base, mutate, name, fragment",
    [case[1:] for case in VALIDATION_CASES],
    ids=[case[0] for case in VALIDATION_CASES],
)
def test_validation_names_the_variable(base, mutate, name, fragment):
    ds = mutate(base())
    with pytest.raises(MediumError) as err:
        validate_medium(ds)
    message = str(err.value)
    assert name in message
    assert fragment in message


def test_validation_accepts_the_bases():
    for make in (micro, optical, tabulated):
        validate_medium(make())


def test_validation_accepts_equivalent_unit_spellings():
    ds = optical()
    ds["cloud_extinction"].attrs["units"] = "1/km"
    ds["x"].attrs["units"] = "kilometre"
    validate_medium(ds)


def test_validation_accepts_both_descriptions_together():
    ds = xr.merge([micro(), optical()[["cloud_extinction", "cloud_albedo", "cloud_g"]]])
    validate_medium(ds)
    assert is_microphysical(ds) and is_optical(ds)


def test_validation_rejects_non_dataset():
    with pytest.raises(MediumError, match="xarray.Dataset"):
        validate_medium(micro()["lwc"])


# ---------------------------------------------------------------------------------------
# netCDF
# ---------------------------------------------------------------------------------------


def _rich_micro() -> xr.Dataset:
    lwc = _lwc()
    veff = np.where(lwc > 0, 0.12, 0.0)
    air = np.linspace(0.05, 0.03, NZ)
    return microphysical_medium(
        X,
        Y,
        Z_BOUNDS.mean(axis=1),
        lwc,
        np.where(lwc > 0, 11.0, 0.0),
        veff=veff,
        z_bounds=Z_BOUNDS,
        air_extinction=air,
        title="round trip",
        source="test",
    )


def _rich_optical() -> xr.Dataset:
    ds = tabulated()
    air = np.full((NX, NY, NZ), 0.04)
    air[0] = 0.05
    return optical_medium(
        X,
        Y,
        Z,
        ds["cloud_extinction"].values,
        cloud_albedo=np.full((NX, NY, NZ), 0.999),
        cloud_phase=(ds["cloud_phase"].values, ANGLES),
        cloud_phase_index=ds["cloud_phase_index"].values,
        air_extinction=air,
        wavelength=0.672,
    )


@pytest.mark.parametrize("make", [_rich_micro, _rich_optical], ids=["microphysical", "optical"])
def test_netcdf_round_trip(tmp_path, make):
    ds = make()
    path = tmp_path / "medium.nc"
    save_medium(ds, path)
    back = load_medium(path)
    xr.testing.assert_identical(back, ds)  # values, coordinates, variable and global attrs
    for name in ds.variables:
        assert back[name].dtype == ds[name].dtype, name
        assert "_FillValue" not in back[name].attrs, name
    assert back.attrs == ds.attrs


def test_round_trip_keeps_integer_phase_index(tmp_path):
    save_medium(tabulated(), tmp_path / "m.nc")
    assert load_medium(tmp_path / "m.nc")["cloud_phase_index"].dtype == np.int32


def test_save_refuses_to_overwrite(tmp_path):
    path = tmp_path / "medium.nc"
    save_medium(micro(), path)
    with pytest.raises(FileExistsError, match="overwrite"):
        save_medium(optical(), path)
    assert is_microphysical(load_medium(path))
    save_medium(optical(), path, overwrite=True)
    assert is_optical(load_medium(path))
    assert [p.name for p in tmp_path.iterdir()] == ["medium.nc"]


def test_save_refuses_invalid_medium(tmp_path):
    with pytest.raises(MediumError, match="cloud_albedo"):
        save_medium(optical().assign(cloud_albedo=2.0), tmp_path / "bad.nc")
    assert not (tmp_path / "bad.nc").exists()


def test_load_validates(tmp_path):
    path = tmp_path / "bad.nc"
    optical().assign(cloud_g=1.5).to_netcdf(path)
    with pytest.raises(MediumError, match="cloud_g"):
        load_medium(path)
