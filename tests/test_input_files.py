"""Broken input files end in one line that names the file, from every command.

Truncated, empty and non-netCDF files, and netCDF files that hold something else, given
as a medium, a scene, measurements, a result or a checkpoint: ``cloudct`` exits with
status 2 and one line on stderr naming the file, never a traceback.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from cloudct.cli import main
from cloudct.mc.render import single_cloud_medium
from cloudct.medium import save_medium


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("inputs")
    medium = d / "medium.nc"
    save_medium(single_cloud_medium(), medium)
    data = medium.read_bytes()
    out = {"medium": medium}
    out["truncated"] = d / "truncated.nc"
    out["truncated"].write_bytes(data[: len(data) // 2])
    out["empty"] = d / "empty.nc"
    out["empty"].write_bytes(b"")
    out["text"] = d / "text.nc"
    out["text"].write_text("x y z lwc reff\n1 2 3 0.1 10\n")
    out["other"] = d / "other.nc"  # valid netCDF, holding something else
    xr.Dataset({"a": ("t", np.arange(3.0))}).to_netcdf(out["other"])
    return out


def run(argv: list[str], capsys) -> str:
    status = main(argv)
    err = capsys.readouterr().err.strip()
    assert status == 2, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


@pytest.mark.parametrize("bad", ["truncated", "empty", "text", "other"])
@pytest.mark.parametrize("role", ["medium", "scene", "measurements", "result", "checkpoint"])
def test_broken_input_is_one_line_naming_the_file(files, tmp_path, capsys, bad, role):
    path = str(files[bad])
    medium = str(files["medium"])
    argv = {
        "medium": ["render", path, "-o", str(tmp_path / "images.nc")],
        "scene": ["render", medium, "--scene", path, "-o", str(tmp_path / "images.nc")],
        "measurements": ["carve", path, "-o", str(tmp_path / "init.nc")],
        "result": ["report", path, "-o", str(tmp_path / "report")],
        "checkpoint": None,
    }[role]
    if role == "checkpoint":
        measurements = tmp_path / "measurements.nc"
        assert main(["synth", medium, "-o", str(measurements), "--photons", "2000"]) == 0
        capsys.readouterr()
        argv = ["retrieve", str(measurements), "--init", medium, "--resume",
                "--checkpoint", path, "-o", str(tmp_path / "result.nc")]
    err = run(argv, capsys)
    assert path in err
    if bad != "other":
        assert "cannot be read as netCDF" in err


def test_missing_input_is_one_line(files, tmp_path, capsys):
    missing = str(tmp_path / "nowhere.nc")
    err = run(["render", missing, "-o", str(tmp_path / "images.nc")], capsys)
    assert missing in err and "does not exist" in err


# ---------------------------------------------------------------------------------------
# Convertible units are refused with the conversion to make (cloudct.units)
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("variable, units, factor", [
    ("lwc", "kg m-3", "1000"),  # the test only relabels the values: the message is checked
    ("reff", "m", "1e+06"),
    ("x", "m", "0.001"),
    ("air_extinction", "1/m", "1000"),
])
def test_a_medium_in_other_units_is_refused_with_the_conversion(tmp_path, capsys, variable,
                                                                units, factor):
    medium = single_cloud_medium()
    medium[variable].attrs["units"] = units
    path = tmp_path / "medium.nc"
    medium.to_netcdf(path)
    err = run(["render", str(path), "-o", str(tmp_path / "images.nc")], capsys)
    assert str(path) in err and f"multiply {variable} by {factor} " in err, err


def test_a_measurement_file_in_metres_is_refused_with_the_conversion(files, tmp_path, capsys):
    measurements = tmp_path / "measurements.nc"
    assert main(["synth", str(files["medium"]), "--photons", "2000", "-o",
                 str(measurements)]) == 0
    ds = xr.load_dataset(measurements)
    ds["position"] = ds["position"] * 1000.0
    ds["position"].attrs["units"] = "m"
    ds.to_netcdf(tmp_path / "in_metres.nc")
    err = run(["carve", str(tmp_path / "in_metres.nc"), "-o", str(tmp_path / "init.nc")], capsys)
    assert "position has units 'm'" in err and "multiply position by 0.001" in err, err
    ds["position"].attrs["units"] = "furlong"
    ds.to_netcdf(tmp_path / "in_furlongs.nc")
    err = run(["carve", str(tmp_path / "in_furlongs.nc"), "-o", str(tmp_path / "init.nc")],
              capsys)
    assert "position has units 'furlong'; expected 'km'" in err, err
