"""Damaged inputs, generated (hypothesis, derandomised: the same examples every run).

Media, scenes, measurement files, LES text files and retrieval settings files are
truncated, have bytes overwritten, lose variables or get other units; every command that reads
one either works (writing no NaN) or ends with exit status 2 and one line on stderr, never a
traceback."""

from __future__ import annotations

import contextlib
import io
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_score_gradient import gradient_medium, gradient_scene

import cloudct
from cloudct.cli import main
from cloudct.mc.render import render
from cloudct.measurements import save_measurements
from cloudct.medium import save_medium

EXAMPLES = settings(max_examples=20, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow])
LES = Path(cloudct.__file__).parent / "data" / "rico32x37x26.txt"


@pytest.fixture(scope="module")
def valid(tmp_path_factory) -> dict[str, Path]:
    """One valid file of each kind."""
    d = tmp_path_factory.mktemp("valid")
    files = {"medium": d / "medium.nc", "scene": d / "scene.nc",
             "measurements": d / "measurements.nc", "les": d / "les.txt",
             "config": d / "run.toml"}
    save_medium(gradient_medium(), files["medium"])
    gradient_scene().to_dataset().to_netcdf(files["scene"])
    save_measurements(render(gradient_medium(), gradient_scene(), photons=20_000, seed=3,
                             progress=False), files["measurements"])
    shutil.copy(LES, files["les"])
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["retrieve", "--write-config"]) == 0
    files["config"].write_text(out.getvalue())
    return files


def _commands(kind: str, bad: Path, valid: dict[str, Path], out: Path) -> tuple[list, dict]:
    """The command that reads a file of ``kind`` (the damaged one at ``bad``), and the
    variables of what it writes that must hold no NaN."""
    if kind == "medium":
        return ["scene", str(bad), "-o", str(out / "s.nc")], {out / "s.nc": ["position"]}
    if kind == "scene":
        return (["render", str(valid["medium"]), "--scene", str(bad), "--photons", "64",
                 "--backend", "cpu", "-o", str(out / "i.nc")], {out / "i.nc": ["radiance"]})
    if kind == "measurements":
        return (["retrieve", str(bad), "--init", str(valid["medium"]), "--iterations", "0",
                 "--backend", "cpu", "-o", str(out / "r.nc")],
                {out / "r.nc": ["cloud_extinction"]})
    if kind == "les":
        return ["les2nc", str(bad), "-o", str(out / "m.nc")], {out / "m.nc": ["lwc", "reff"]}
    return ["retrieve", "--config", str(bad), "--write-config"], {}


def _one_line_or_no_nan(argv: list[str], outputs: dict[Path, list[str]]) -> None:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        status = main(argv)
    lines = err.getvalue().strip().splitlines()
    if status == 0:
        for path, names in outputs.items():
            ds = xr.load_dataset(path)
            for name in names:
                assert np.isfinite(ds[name].values).all(), f"{name} of {path} has NaN or inf"
        return
    assert status == 2, err.getvalue()
    assert len(lines) == 1 and "Traceback" not in lines[0], err.getvalue()
    assert lines[0].startswith(f"cloudct {argv[0]}: error: "), lines[0]


def _damaged_bytes(data: bytes, cut: float | None, flips: list[tuple[float, int]]) -> bytes:
    if cut is not None:
        return data[: int(cut * len(data))]
    out = bytearray(data)
    for where, value in flips:
        out[min(int(where * len(out)), len(out) - 1)] = value
    return bytes(out)


BYTE_DAMAGE = st.one_of(
    st.tuples(st.floats(0.0, 0.999), st.just([])),  # truncated
    st.tuples(st.none(), st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(0, 255)),
                                  min_size=1, max_size=8)),  # bytes overwritten
)


@pytest.mark.parametrize("kind", ["medium", "scene", "measurements", "les", "config"])
@EXAMPLES
@given(damage=BYTE_DAMAGE)
def test_truncated_or_overwritten_files(valid, kind, damage):
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        bad = tmp / f"bad{valid[kind].suffix}"
        bad.write_bytes(_damaged_bytes(valid[kind].read_bytes(), *damage))
        argv, outputs = _commands(kind, bad, valid, tmp)
        _one_line_or_no_nan(argv, outputs)


UNITS = st.sampled_from(["m", "km", "1/m", "m-1", "g/kg", "furlong", "", "degrees", "K"])


@pytest.mark.parametrize("kind", ["medium", "scene", "measurements"])
@EXAMPLES
@given(data=st.data())
def test_netcdf_files_missing_variables_or_in_other_units(valid, kind, data):
    ds = xr.load_dataset(valid[kind])
    names = sorted(ds.variables)
    dropped = data.draw(st.lists(st.sampled_from(names), max_size=3, unique=True))
    relabelled = data.draw(st.dictionaries(st.sampled_from(names), UNITS, max_size=3))
    for name, units in relabelled.items():
        ds[name].attrs["units"] = units
    ds = ds.drop_vars([n for n in dropped if n in ds.variables])
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        bad = tmp / "bad.nc"
        ds.to_netcdf(bad)
        argv, outputs = _commands(kind, bad, valid, tmp)
        _one_line_or_no_nan(argv, outputs)
