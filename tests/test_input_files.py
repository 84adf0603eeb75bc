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
