"""LES readers, the bundled single cloud and cloud field, the seed paper's cloud-field
window and the ``les2nc`` command."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import cloudct.cli
from cloudct.cli.media import register_cli
from cloudct.les import (
    BUNDLED_FIELD_SOURCE,
    BUNDLED_SOURCE,
    SEED_PAPER_FIELD_SHAPE,
    LESFormatError,
    bundled_cloud_field,
    bundled_single_cloud,
    densest_window,
    read_jpl_les,
    read_les,
    read_shdom_particle_file,
    seed_paper_cloud_field,
)
from cloudct.mc.render import single_cloud_medium
from cloudct.medium import cell_edges, domain_bounds, load_medium
from cloudct.optics import DEFAULT_OPTICS, OPTICS, to_optical

REPO = Path(__file__).resolve().parents[1]
BUNDLED = REPO / "cloudct" / "data" / "rico32x37x26.txt"
# The shared LES files sit next to the repository (../shared/data/les) unless told otherwise.
LES_DIR = Path(os.environ.get("CLOUDCT_LES_DIR", REPO.parent / "shared" / "data" / "les"))
needs_shared = pytest.mark.skipif(
    not (LES_DIR / "les_stcu.txt").exists(), reason=f"shared LES files not found in {LES_DIR}"
)


def _plain_cloud_stats(path: Path, first_row: int, sep: str | None) -> tuple[float, int]:
    """Maximum LWC and number of cells with LWC > 0, parsed here with plain Python."""
    max_lwc, cloudy = 0.0, 0
    with open(path) as f:
        for number, line in enumerate(f, start=1):
            if number < first_row or not line.strip():
                continue
            lwc = float(line.split(sep)[3])
            max_lwc = max(max_lwc, lwc)
            cloudy += lwc > 0
    return max_lwc, cloudy


@pytest.fixture(scope="module")
def single_cloud():
    return read_jpl_les(BUNDLED)


def test_rico32_grid(single_cloud):
    ds = single_cloud
    assert (ds.sizes["x"], ds.sizes["y"], ds.sizes["z"]) == (32, 37, 26)
    assert "z_bounds" not in ds  # uniform 40 m layers
    x_edges, y_edges, z_edges = cell_edges(ds)
    np.testing.assert_allclose(np.diff(x_edges), 0.02)
    np.testing.assert_allclose(np.diff(y_edges), 0.02)
    np.testing.assert_allclose(np.diff(z_edges), 0.04)
    np.testing.assert_allclose(ds["x"].values[:2], [0.01, 0.03])
    np.testing.assert_allclose(ds["z"].values[[0, -1]], [0.46, 1.46])
    bounds = domain_bounds(ds)
    assert bounds.x_min == pytest.approx(0.0) and bounds.x_max == pytest.approx(0.64)
    assert bounds.y_min == pytest.approx(0.0) and bounds.y_max == pytest.approx(0.74)
    assert bounds.z_min == pytest.approx(0.44) and bounds.z_max == pytest.approx(1.48)


def test_rico32_content_matches_plain_parse(single_cloud):
    max_lwc, cloudy = _plain_cloud_stats(BUNDLED, first_row=6, sep=",")
    assert float(single_cloud["lwc"].max()) == max_lwc
    assert int((single_cloud["lwc"] > 0).sum()) == cloudy
    assert cloudy == 3943
    clear = single_cloud["lwc"].values == 0
    assert np.all(single_cloud["reff"].values[clear] == 0)
    assert np.all(single_cloud["reff"].values[~clear] > 0)


def test_rico32_a_known_row(single_cloud):
    # Row "2,2,4,0.00675,12.52100" of the file.
    cell = single_cloud.isel(x=2, y=2, z=4)
    assert float(cell["lwc"]) == 0.00675
    assert float(cell["reff"]) == 12.521


def test_bundled_single_cloud_is_the_shared_file(single_cloud):
    ds = bundled_single_cloud()
    assert ds.attrs["source"] == BUNDLED_SOURCE
    assert "pyshdom" in ds.attrs["source"] and "JPL" in ds.attrs["source"]
    np.testing.assert_array_equal(ds["lwc"].values, single_cloud["lwc"].values)
    if (LES_DIR / "rico32x37x26.txt").exists():
        assert (LES_DIR / "rico32x37x26.txt").read_bytes() == BUNDLED.read_bytes()


def test_bundled_cloud_field_is_the_shared_file():
    field = bundled_cloud_field()
    assert field.attrs["source"] == BUNDLED_FIELD_SOURCE
    assert "pyshdom" in field.attrs["source"] and "JPL" in field.attrs["source"]
    assert field["lwc"].shape == (122, 106, 39)
    shared = LES_DIR / "rico122x106x39.txt"
    if shared.exists():
        assert shared.read_bytes() == (BUNDLED.parent / "rico122x106x39.txt").read_bytes()


def test_densest_window_is_the_window_of_the_largest_sum():
    field = np.random.default_rng(5).uniform(size=(9, 7, 6))
    shape = (4, 3, 5)
    sums = {(i, j, k): field[i:i + 4, j:j + 3, k:k + 5].sum()
            for i in range(6) for j in range(5) for k in range(2)}
    assert densest_window(field, shape) == max(sums, key=sums.get)
    assert densest_window(np.ones((5, 5, 5)), (2, 2, 2)) == (0, 0, 0)  # ties: the first
    with pytest.raises(ValueError, match="does not fit"):
        densest_window(field, (10, 3, 5))


def test_seed_paper_cloud_field_is_the_window_of_the_most_cloudy_cells():
    """79 x 84 x 27 cells (1.58 x 1.68 x 1.08 km, the seed paper's Table 1) at cells
    x 39..117, y 14..97, z 3..29 of rico122x106x39, in the LES domain's coordinates; no
    window one cell over along any axis holds more cloudy cells."""
    field, crop = bundled_cloud_field(), seed_paper_cloud_field()
    assert crop["lwc"].shape == SEED_PAPER_FIELD_SHAPE == (79, 84, 27)
    edges = cell_edges(crop)
    np.testing.assert_allclose([e[-1] - e[0] for e in edges], [1.58, 1.68, 1.08], rtol=1e-9)
    np.testing.assert_allclose([e[0] for e in edges], [0.78, 0.28, 0.56], rtol=1e-9)
    window = {"x": slice(39, 118), "y": slice(14, 98), "z": slice(3, 30)}
    np.testing.assert_array_equal(crop["lwc"].values, field["lwc"].isel(window).values)
    assert "rico122x106x39" in crop.attrs["source"] and "x 39..117" in crop.attrs["source"]
    cloudy = field["lwc"].values > 0
    best = cloudy[39:118, 14:98, 3:30].sum()
    for axis in range(3):
        for shift in (-1, 1):
            start = np.array([39, 14, 3])
            start[axis] += shift
            other = cloudy[tuple(slice(a, a + n) for a, n in zip(start, (79, 84, 27), strict=True))]
            assert other.sum() <= best


@needs_shared
def test_rico122_shape_and_i_j_k_header():
    path = LES_DIR / "rico122x106x39.txt"
    ds = read_les(path)
    assert (ds.sizes["x"], ds.sizes["y"], ds.sizes["z"]) == (122, 106, 39)
    assert domain_bounds(ds).z_max == pytest.approx(2.0)
    max_lwc, cloudy = _plain_cloud_stats(path, first_row=6, sep=",")
    assert float(ds["lwc"].max()) == max_lwc
    assert int((ds["lwc"] > 0).sum()) == cloudy


@needs_shared
def test_les_stcu_shape_and_non_uniform_z():
    path = LES_DIR / "les_stcu.txt"
    ds = read_les(path)
    assert (ds.sizes["x"], ds.sizes["y"], ds.sizes["z"]) == (64, 64, 16)
    with open(path) as f:
        f.readline()
        f.readline()
        levels = [float(v) for v in f.readline().split()[2:]]
    expected_edges = levels + [levels[-1] + (levels[-1] - levels[-2])]
    assert ds["z"].attrs["bounds"] == "z_bounds"
    np.testing.assert_allclose(ds["z_bounds"].values[:, 0], levels, rtol=0, atol=1e-12)
    np.testing.assert_allclose(cell_edges(ds)[2], expected_edges, rtol=0, atol=1e-12)
    assert domain_bounds(ds).z_max == pytest.approx(0.836)
    assert np.ptp(np.diff(cell_edges(ds)[2])) > 1e-3  # genuinely non-uniform
    np.testing.assert_allclose(np.diff(cell_edges(ds)[0]), 0.055)
    max_lwc, cloudy = _plain_cloud_stats(path, first_row=4, sep=None)
    assert float(ds["lwc"].max()) == max_lwc
    assert int((ds["lwc"] > 0).sum()) == cloudy


# ---------------------------------------------------------------------------------------
# Small hand-written files
# ---------------------------------------------------------------------------------------

JPL_HEADER = "# tiny test cloud\n3,2,2   # nx,ny,nz\n0.05,0.05  # dx,dy\n0.5,0.6  # levels\n"
SHDOM_HEADER = "# tiny SHDOM cloud\n2 2 3\n0.1 0.1 0.0 0.2 0.5\n"


def _write(tmp_path: Path, text: str, name: str = "cloud.txt") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_small_jpl_file_with_veff_column(tmp_path):
    text = JPL_HEADER + "i,j,k,lwc,reff,veff\n0,1,1,0.2,10.0,0.05\n\n2,0,0,0.1,8.0,0.1\n"
    ds = read_les(_write(tmp_path, text))
    assert ds["lwc"].values[0, 1, 1] == 0.2 and ds["veff"].values[2, 0, 0] == 0.1
    assert ds.attrs["title"] == "tiny test cloud"
    assert "cloud.txt" in ds.attrs["source"]
    np.testing.assert_allclose(ds["x"].values, [0.025, 0.075, 0.125])
    np.testing.assert_allclose(cell_edges(ds)[2], [0.5, 0.6, 0.7])


def test_small_shdom_file(tmp_path):
    rows = "0 0 0 0.0 0.0\n1 1 2 0.3 9.0\n0 1 1 0.0 4.0\n"
    ds = read_shdom_particle_file(_write(tmp_path, SHDOM_HEADER + rows))
    np.testing.assert_allclose(ds["z_bounds"].values, [[0.0, 0.2], [0.2, 0.5], [0.5, 0.8]])
    np.testing.assert_allclose(ds["z"].values, [0.1, 0.35, 0.65])
    assert ds["lwc"].values[1, 1, 2] == 0.3
    assert ds["reff"].values[0, 1, 1] == 4.0  # kept as read: reff is ignored where lwc = 0


def test_read_les_detects_shdom(tmp_path):
    ds = read_les(_write(tmp_path, SHDOM_HEADER + "1 1 2 0.3 9.0\n"))
    assert "SHDOM" in ds.attrs["source"]


_ROW = "x,y,z,lwc,reff\n"
MALFORMED = [
    ("empty", "", 2, "ends"),
    ("short header", "# c\n3,2,2\n", 3, "ends"),
    ("nx,ny,nz count", "# c\n3,2\n0.05,0.05\n0.5,0.6\n" + _ROW, 2, "nx,ny,nz"),
    ("nx,ny,nz text", "# c\n3,a,2\n0.05,0.05\n0.5,0.6\n" + _ROW, 2, "non-numeric"),
    ("negative dx", "# c\n3,2,2\n-0.05,0.05\n0.5,0.6\n" + _ROW, 3, "positive"),
    ("missing z level", "# c\n3,2,2\n0.05,0.05\n0.5\n" + _ROW, 4, "z levels"),
    ("decreasing levels", "# c\n3,2,2\n0.05,0.05\n0.6,0.5\n" + _ROW, 4, "increasing"),
    ("bad header", JPL_HEADER + "x,y,z,lwc,re\n", 5, "bad header"),
    ("fields", JPL_HEADER + _ROW + "0,0,0,0.1\n", 6, "expected 5 fields"),
    ("non-numeric", JPL_HEADER + _ROW + "0,0,0,0.1,10\n1,1,1,abc,10\n", 7, "non-numeric"),
    ("non-integer index", JPL_HEADER + _ROW + "0,0.5,0,0.1,10\n", 6, "not an integer"),
    ("index range", JPL_HEADER + _ROW + "0,0,0,0.1,10\n3,0,0,0.1,10\n", 7, "out of range"),
    ("negative index", JPL_HEADER + _ROW + "0,0,-1,0.1,10\n", 6, "out of range"),
    ("duplicate", JPL_HEADER + _ROW + "0,0,0,0.1,10\n1,1,1,0.1,10\n0,0,0,0.2,9\n", 8, "line 6"),
    ("negative lwc", JPL_HEADER + _ROW + "0,0,0,-0.1,10\n", 6, "negative LWC"),
    ("negative reff", JPL_HEADER + _ROW + "0,0,0,0.0,-1\n", 6, "negative reff"),
    ("reff 0 in cloud", JPL_HEADER + _ROW + "0,0,0,0.2,0\n", 6, "reff = 0"),
    ("nan", JPL_HEADER + _ROW + "0,0,0,nan,10\n", 6, "non-finite"),
    ("shdom levels", "# c\n2 2 3\n0.1 0.1 0.0 0.2\n0 0 0 0.1 10\n", 3, "expected nz = 3"),
    ("shdom fields", SHDOM_HEADER + "0 0 0 0.1 10 3\n", 4, "expected 5 fields"),
    ("shdom range", SHDOM_HEADER + "0 0 3 0.1 10\n", 4, "out of range 0..2"),
]


@pytest.mark.parametrize(
    "text, line, reason",
    [case[1:] for case in MALFORMED],
    ids=[case[0] for case in MALFORMED],
)
def test_malformed_files_name_the_line(tmp_path, text, line, reason):
    path = _write(tmp_path, text, name="bad_les.txt")
    with pytest.raises(LESFormatError) as err:
        read_les(path)
    message = str(err.value)
    assert "bad_les.txt" in message
    assert f"line {line}:" in message
    assert reason in message
    assert err.value.line == line


def test_binary_file_is_a_format_error(tmp_path):
    path = tmp_path / "cloud.bin"
    path.write_bytes(b"# c\n3,2,2\n\xff\xfe\x00\n")
    with pytest.raises(LESFormatError, match="line 3"):
        read_les(path)


# ---------------------------------------------------------------------------------------
# The les2nc command
# ---------------------------------------------------------------------------------------


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="cloudct")
    register_cli(parser.add_subparsers(dest="command"))
    return parser


def test_les2nc_writes_a_medium(tmp_path, capsys, single_cloud):
    out = tmp_path / "medium.nc"
    args = _parser().parse_args(["les2nc", str(BUNDLED), "-o", str(out)])
    assert args.func(args) == 0
    ds = load_medium(out)
    np.testing.assert_array_equal(ds["lwc"].values, single_cloud["lwc"].values)
    assert ds["lwc"].attrs["units"] == "g m-3"
    assert "32 x 37 x 26" in capsys.readouterr().out


def test_les2nc_through_main_refuses_overwrite(tmp_path, monkeypatch, capsys):
    # Only this module's subcommand, so the test does not depend on the others existing.
    monkeypatch.setattr(cloudct.cli, "COMMAND_MODULES", ("cloudct.cli.media",))
    out = tmp_path / "medium.nc"
    text = JPL_HEADER + _ROW + "0,0,0,0.1,10\n"
    src = _write(tmp_path, text)
    assert cloudct.cli.main(["les2nc", str(src), "-o", str(out), "--source", "test LES"]) == 0
    assert load_medium(out).attrs["source"] == "test LES"
    assert cloudct.cli.main(["les2nc", str(src), "-o", str(out)]) == 2
    assert "exists" in capsys.readouterr().err
    assert cloudct.cli.main(["les2nc", str(src), "-o", str(out), "--overwrite"]) == 0


def test_les2nc_reports_malformed_file(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(cloudct.cli, "COMMAND_MODULES", ("cloudct.cli.media",))
    src = _write(tmp_path, JPL_HEADER + _ROW + "0,0,0,-0.1,10\n", name="neg.txt")
    assert cloudct.cli.main(["les2nc", str(src), "-o", str(tmp_path / "m.nc")]) == 2
    err = capsys.readouterr().err
    assert "neg.txt, line 6: negative LWC" in err
    assert not (tmp_path / "m.nc").exists()


# ---------------------------------------------------------------------------------------
# One cloud, one medium: the optics are a recorded choice
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("optics", OPTICS)
def test_les2nc_and_the_bundled_default_give_the_same_medium(tmp_path, capsys, optics):
    out = tmp_path / "medium.nc"
    assert cloudct.cli.main(["les2nc", str(BUNDLED), "-o", str(out), "--optics", optics]) == 0
    assert f"optics {optics!r}" in capsys.readouterr().out
    written = load_medium(out)
    assert written.attrs["optics"] == optics and "cloud_extinction" not in written
    converted, bundled = to_optical(written), single_cloud_medium(optics)
    xr.testing.assert_equal(converted, bundled)  # values, coordinates and variable attrs
    assert converted.attrs["optics"] == bundled.attrs["optics"] == optics
    assert converted.attrs["optics_description"] == bundled.attrs["optics_description"]


def test_the_default_optics_are_the_seed_papers():
    medium = single_cloud_medium()
    assert DEFAULT_OPTICS == "hg" and medium.attrs["optics"] == "hg"
    assert float(medium["cloud_g"]) == 0.85 and np.all(medium["cloud_albedo"].values == 0.99)


def test_every_output_file_names_its_optics(tmp_path):
    """les2nc (mie) -> render and synth of that file -> carve of those measurements: each
    file says 'mie'; an optical medium given other optics is refused."""
    medium = tmp_path / "medium.nc"
    assert cloudct.cli.main(["les2nc", str(BUNDLED), "-o", str(medium), "--optics", "mie"]) == 0
    scene = tmp_path / "scene.nc"
    assert cloudct.cli.main(["scene", str(medium), "--npix", "8", "-o", str(scene)]) == 0
    images = tmp_path / "images.nc"
    assert cloudct.cli.main(["render", str(medium), "--scene", str(scene), "--photons", "2000",
                             "--batches", "4", "-o", str(images)]) == 0
    assert xr.load_dataset(images).attrs["optics"] == "mie"
    synth = tmp_path / "measurements.nc"
    assert cloudct.cli.main(["synth", str(medium), "--scene", str(scene), "--photons", "2000",
                             "-o", str(synth)]) == 0
    assert xr.load_dataset(synth).attrs["optics"] == "mie"
    carved = tmp_path / "init.nc"
    assert cloudct.cli.main(["carve", str(synth), "--medium", str(medium), "--k", "8",
                             "--extinction", "10", "-o", str(carved)]) == 0
    assert load_medium(carved).attrs["optics"] == "mie"
    result = tmp_path / "result.nc"
    # from the carved start above (carving inside retrieve fits the hull's brightness to
    # measurements of 2,000 photons, too noisy to fit on every draw)
    assert cloudct.cli.main(["retrieve", str(synth), "--medium", str(medium), "--init",
                             str(carved), "--iterations", "1", "--photons", "2000", "-o",
                             str(result)]) == 0
    attrs = xr.load_dataset(result).attrs
    assert attrs["optics"] == attrs["measurement_optics"] == "mie"
    optical = tmp_path / "optical.nc"
    single_cloud_medium("hg").to_netcdf(optical)
    assert cloudct.cli.main(["render", str(optical), "--optics", "mie", "--photons", "100",
                             "-o", str(tmp_path / "refused.nc")]) == 2
