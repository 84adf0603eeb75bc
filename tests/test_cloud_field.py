"""Cloud fields through the whole chain: a tiny retrieval of a periodic field from its
space-carved start, and ``cloudct demo --scene cloud-field`` on the seed paper's cloud
field (periodic carving itself is tested in test_carving.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import xarray as xr

from cloudct.cli import main
from cloudct.mc.cameras import nine_camera_set
from cloudct.mc.scene import Scene, build_scene
from cloudct.mc.sun import Sun
from cloudct.measurements import load_measurements, synthesize_measurements
from cloudct.medium import cell_edges, load_medium
from cloudct.retrieval.carving import carve, initial_medium
from cloudct.retrieval.loop import Retrieval, RetrievalConfig
from cloudct.retrieval.metrics import epsilon_delta
from data_synth.synthetic_cloud import blob_cloud


def box(medium) -> tuple[np.ndarray, np.ndarray]:
    edges = cell_edges(medium)
    return np.array([e[0] for e in edges]), np.array([e[-1] for e in edges])


def two_blobs():
    """A periodic 0.28 x 0.28 x 0.32 km field (14 x 14 x 8 voxels): a blob of 15 km-1
    across the x = 0 face (half of it at each side) and one of 22.5 km-1 inside."""
    field = blob_cloud(14, 14, 8, centre=(0.14, 0.07, 0.16), semi_axes=(0.06, 0.05, 0.09),
                       extinction=15.0)
    field["cloud_extinction"].values = np.roll(field["cloud_extinction"].values, 7, axis=0)
    field["cloud_extinction"].values += blob_cloud(
        14, 14, 8, centre=(0.15, 0.2, 0.15), semi_axes=(0.05, 0.05, 0.08), extinction=22.5,
    )["cloud_extinction"].values
    return field


def test_tiny_periodic_retrieval_lowers_epsilon():
    """Periodic boundaries from synthesis to retrieval: nine 16 x 16 views of two blobs,
    carved into the seed paper's start (the hull, 268 voxels for the blobs' 126, filled
    with the fitted constant: epsilon 1.06), then 12 Adam iterations of 10,000 paths at
    full image resolution with voxels tied in 2 x 2 x 2 blocks. Over retrieval seeds 0..9
    epsilon fell by 0.224 on average with a run-to-run standard deviation of 0.031 (least
    0.191; seed 0, tested: 0.226): the test asks for a fall of 0.1, 4 standard deviations
    below the mean and 3 above 0. (Measured with the step, prior and image photons given
    here, retrieve's defaults of the time.) (The excess-profile start, epsilon 0.60, is already as
    good as such small images tell: a dozen iterations leave it within the noise.)"""
    field = two_blobs()
    scene = Scene(nine_camera_set(*box(field), npix=16), Sun(0.0, 0.0), "periodic")
    measured = synthesize_measurements(field, scene, photons=400_000, seed=1, progress=False)
    carved = carve(measured, field, profile="constant", fit_photons=20_000)
    start = initial_medium(carved, field)
    truth = field["cloud_extinction"].values
    eps0, _ = epsilon_delta(truth, start["cloud_extinction"].values)
    config = RetrievalConfig(iterations=12, photons=10_000, stages=(1,), voxel_blocks=(2,),
                             seed=0, step=1.0, priors=(), image_photons=(4.0,))
    result = Retrieval(measured, start, config, truth=field).run(progress=False)
    eps = result["log_epsilon"].values
    print(f"hull {int(carved['hull'].sum())} voxels (blobs {int((truth > 0).sum())}); "
          f"epsilon {eps0:.3f} -> {np.round(eps, 3)}")
    assert eps0 - eps[-1] > 0.1


def test_cli_demo_on_the_cloud_field(tmp_path, capsys):
    """``cloudct demo --scene cloud-field`` at tiny photon counts: the files are written,
    the truth is the seed paper's 79 x 84 x 27 cloud field, the cameras are build_scene's
    ``cloud-field`` preset (nine 86 x 86 views, open boundaries), and the run's settings
    are retrieve's defaults, like the single cloud's but for the iterations' time, with
    the options given. An unknown scene is refused."""
    out = tmp_path / "field"
    argv = ["demo", "--scene", "cloud-field", "-o", str(out), "--measurement-photons",
            "1000000", "--iterations", "1", "--photons", "2000"]
    assert main(argv) == 0
    assert "cloud-field: 79 x 84 x 27 voxels" in capsys.readouterr().out
    for name in ("measurements.nc", "truth.nc", "init.nc", "result.nc", "checkpoint.nc",
                 "report/summary.md"):
        assert (out / name).is_file(), name
    truth = load_medium(out / "truth.nc")
    assert truth["cloud_extinction"].shape == (79, 84, 27)
    assert "rico122x106x39" in truth.attrs["source"]
    measured = Scene.from_dataset(load_measurements(out / "measurements.nc"))
    preset = build_scene(*box(truth), preset="cloud-field")
    assert measured.boundary == preset.boundary == "open"
    assert len(measured.cameras) == 9
    for got, expected in zip(measured.cameras, preset.cameras, strict=True):
        np.testing.assert_allclose(got.position, expected.position, rtol=1e-12)
        assert (got.fov, got.nrows, got.ncols) == pytest.approx(
            (expected.fov, expected.nrows, expected.ncols), rel=1e-12)
        assert got.nrows == 86
    result = xr.load_dataset(out / "result.nc")
    assert RetrievalConfig(**json.loads(result.attrs["config"])) == RetrievalConfig(
        iterations=1, photons=2_000)

    assert main(["demo", "--scene", "cloud-field", "--write-config"]) == 0
    field = capsys.readouterr().out
    assert 'photons = "auto"' in field and "step = 0.5" in field
    assert main(["demo", "--write-config"]) == 0
    single = capsys.readouterr().out
    assert "iterations = 120" in single and "step = 0.5" in single
    assert "# iteration_seconds = 5.0" in field and "# [[prior]]" in field
    assert "iterations = 120" in field
    with pytest.raises(SystemExit) as refused:
        main(["demo", "--scene", "cumulus", "-o", str(tmp_path / "other")])
    assert refused.value.code == 2
    assert "invalid choice: 'cumulus'" in capsys.readouterr().err
