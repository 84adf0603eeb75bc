"""Sensors beyond pinholes: domain-mean fluxes, radiance probes and orthographic cameras.

- A periodic homogeneous slab (the one of tests/test_plane_parallel.py, with and without a
  Lambertian ground) against the independent adding-doubling solver
  (tests/reference/plane_parallel.py): probe radiances in reflected and transmitted
  directions, and the albedo, direct and diffuse transmittance and absorptance.
- Energy closure: a conservative slab over a white ground returns everything (albedo 1);
  an absorbing open box with a grey ground balances albedo + absorptance + side escape +
  ground absorption = 1; an empty open box against its geometry (direct transmittance,
  side escape and the ground's radiance seen by a probe, in closed form).
- Orthographic cameras: on the slab every pixel has the probe's radiance, forward and
  backward; forward (plain and aimed at the cameras) against backward on a heterogeneous
  open box; the DRT and sample-matching gradients against the score-function gradient
  (camera paths from the image rectangle against local estimates projected onto it);
  stored paths replayed under the reference medium against the forward renderer and the
  score-function gradient; the projection against the conventions; the scene's netCDF
  round trip; clear errors for the setups that cannot work.

Russian roulette starts early in the closure tests (``rr_depth`` 3-5) so that the balances
carry real noise and test the roulette's weights too.
"""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr
from mcstats import assert_consistent
from reference.plane_parallel import rayleigh_hg_mixture, slab_fluxes, slab_radiances
from test_forward import uniform_axis
from test_plane_parallel import SLAB, SUN, slab_medium

from cloudct.cli import main
from cloudct.mc.cameras import (
    Camera,
    camera_arrays,
    orthographic_camera,
    pixel_ray,
    project,
    travel_direction,
)
from cloudct.mc.estimate import kernel_inputs
from cloudct.mc.forward import FLUX_GROUND, FLUX_MEDIUM, FLUX_SIDE, FLUX_TOP, NFLUX, sensor_batches
from cloudct.mc.gradient import drt_gradient, sample_matching_gradient, score_function_gradient
from cloudct.mc.render import render, render_batches
from cloudct.mc.scene import Scene
from cloudct.mc.sensors import domain_means
from cloudct.mc.sun import Sun
from cloudct.medium import optical_medium, save_medium
from cloudct.recycling import record_paths, replay_gradient, replay_images

# (zenith, azimuth) of the light's propagation: < 90 reflected, > 90 transmitted
DIRECTIONS = [(0.0, 0.0), (35.0, 0.0), (35.0, 180.0), (60.0, 90.0), (180.0, 0.0),
              (140.0, 180.0), (150.0, 45.0)]
CENTRE = (0.5, 0.5, 0.5)


def slab_reference(directions, ground: float | None = None):
    """Probe radiances and flux shares of the slab from the adding-doubling solver."""
    beta = SLAB["beta_air"] + SLAB["beta_cloud"]
    bs_air = SLAB["albedo_air"] * SLAB["beta_air"]
    bs_cloud = SLAB["albedo_cloud"] * SLAB["beta_cloud"]
    args = (beta * SLAB["top"], (bs_air + bs_cloud) / beta,
            rayleigh_hg_mixture(bs_air, bs_cloud, SLAB["g"]), np.cos(np.radians(SUN.zenith)))
    zenith, azimuth = np.array(directions, float).T
    up = zenith < 90.0
    # the reference's transmitted view angle is measured from the nadir
    reflected, transmitted = slab_radiances(*args, SUN.azimuth, np.where(up, zenith, 180 - zenith),
                                            azimuth, surface_albedo=ground or 0.0)
    flux = slab_fluxes(*args, surface_albedo=ground or 0.0)
    mu0 = args[3]
    shares = {"albedo": flux.reflected / mu0, "transmittance_direct": flux.transmitted_direct / mu0,
              "transmittance_diffuse": flux.transmitted_diffuse / mu0}
    # absorbed in the slab = what comes in - what leaves the top - the net flux at the bottom
    down = shares["transmittance_direct"] + shares["transmittance_diffuse"]
    shares["absorptance"] = 1.0 - shares["albedo"] - down * (1.0 - (ground or 0.0))
    return np.where(up, reflected, transmitted), shares


@pytest.mark.parametrize("ground", [None, 0.3])
def test_slab_probes_and_fluxes_match_the_plane_parallel_reference(ground):
    means = domain_means(slab_medium(), directions=DIRECTIONS, sun=SUN, boundary="periodic",
                         ground_albedo=ground, photons=320_000, seed=11, progress=False)
    radiance, shares = slab_reference(DIRECTIONS, ground)
    label = f"slab probes, ground {ground}"
    assert_consistent(means.radiance.values, means.radiance_std_error.values, radiance,
                      means.attrs["batches"], label=label)
    assert np.all(means.radiance_std_error.values < 0.02 * radiance)  # the test has power
    # (the absorptance is 1 - the rest, photon by photon: tested apart)
    for names in (["albedo", "transmittance_direct", "transmittance_diffuse"], ["absorptance"]):
        assert_consistent(np.array([float(means[n]) for n in names]),
                          np.array([float(means[f"{n}_std_error"]) for n in names]),
                          np.array([shares[n] for n in names]), means.attrs["batches"],
                          label=f"slab {', '.join(names)}, ground {ground}")
    assert float(means.side_escape) == 0.0
    ground_share = float(means.ground_absorptance)
    assert (ground_share == 0.0) if ground is None else ground_share > 0.0
    assert means.radiance.attrs["units"] == "1" and "long_name" in means.albedo.attrs


def test_conservative_slab_over_a_white_ground_returns_everything():
    medium = optical_medium(
        uniform_axis(0.0, 1.0, 2), uniform_axis(0.0, 1.0, 2), uniform_axis(0.0, 1.0, 4),
        np.full((2, 2, 4), SLAB["beta_cloud"]), cloud_albedo=1.0, cloud_g=SLAB["g"],
        air_extinction=SLAB["beta_air"], air_albedo=1.0,
    )
    means = domain_means(medium, sun=SUN, boundary="periodic", ground_albedo=1.0,
                         photons=64_000, seed=4, rr_depth=5, progress=False)
    assert float(means.albedo_std_error) > 1e-4  # the roulette's noise: a real test
    assert_consistent(float(means.albedo), float(means.albedo_std_error), 1.0,
                      means.attrs["batches"], label="white ground, conservative slab")
    for name in ("absorptance", "ground_absorptance", "side_escape"):
        assert float(means[name]) == 0.0, name


def test_open_box_balances_its_energy():
    rng = np.random.default_rng(5)
    axis = 0.1 + 0.2 * np.arange(4)
    medium = optical_medium(axis, axis, axis + 0.2, rng.uniform(0.0, 8.0, (4, 4, 4)),
                            cloud_albedo=0.9, air_extinction=0.5, air_albedo=0.8)
    means = domain_means(medium, directions=[(20.0, 10.0), (130.0, 250.0)],
                         sun=Sun(50.0, 30.0), boundary="open", ground_albedo=0.4,
                         photons=64_000, seed=6, rr_depth=3, progress=False)
    assert float(means.energy_balance_std_error) > 1e-4
    assert_consistent(float(means.energy_balance), float(means.energy_balance_std_error), 1.0,
                      means.attrs["batches"], label="open box energy balance")
    for name in ("albedo", "transmittance_direct", "transmittance_diffuse", "absorptance",
                 "side_escape", "ground_absorptance"):
        assert float(means[name]) > 0.0, name


def test_empty_open_box_against_its_geometry():
    """No extinction: a photon goes straight from its sunlit face to the bottom or a side;
    the bottom's share is its projected area over the sunlit faces'; the ground plate's
    radiance A mu0 / pi, seen by an upward probe, is weighted by the plate's share of the
    box's silhouette; nothing travels down but the direct beam."""
    axis = 0.1 + 0.2 * np.arange(3)
    medium = optical_medium(axis, axis, 0.1 + 0.1 * np.arange(2), np.zeros((3, 3, 2)),
                            air_extinction=0.0)
    sun, ground, view = Sun(40.0, 60.0), 0.5, (50.0, 200.0)
    means = domain_means(medium, directions=[view, (150.0, 0.0)], sun=sun, boundary="open",
                         ground_albedo=ground, photons=64_000, seed=8, progress=False)
    lx, lz = 0.6, 0.2
    s = sun.travel_direction()
    w = travel_direction(*view)
    bottom = lx * lx * -s[2] / (lx * lx * -s[2] + lx * lz * (abs(s[0]) + abs(s[1])))
    silhouette = lx * lx * w[2] + lx * lz * (abs(w[0]) + abs(w[1]))
    probe = ground * -s[2] / np.pi * lx * lx * w[2] / silhouette
    names = ["transmittance_direct", "ground_absorptance"]
    assert_consistent(
        np.array([*(float(means[n]) for n in names), means.radiance.values[0]]),
        np.array([*(float(means[f"{n}_std_error"]) for n in names),
                  means.radiance_std_error.values[0]]),
        np.array([bottom, bottom * (1.0 - ground), probe]),
        means.attrs["batches"], label="empty open box",
    )
    assert float(means.transmittance_diffuse) == 0.0 and means.radiance.values[1] == 0.0
    assert abs(float(means.energy_balance) - 1.0) < 1e-12


def test_orthographic_camera_sees_the_slab_probe_radiance():
    """Each pixel of an orthographic camera over the periodic slab is the domain mean:
    forward and backward against the reference, and against each other."""
    views = [(35.0, 180.0), (140.0, 180.0)]
    cams = [orthographic_camera(CENTRE, z, a, width=1.0, nrows=2, distance=3.0)
            for z, a in views]
    scene = Scene(cams, SUN, "periodic")
    reference = np.broadcast_to(slab_reference(views)[0][:, None, None], (2, 2, 2))
    images = {method: render(slab_medium(), scene, photons=n, method=method, seed=12,
                             progress=False)
              for method, n in (("forward", 400_000), ("backward", 48_000))}
    for method, im in images.items():
        assert_consistent(im.radiance.values, im.radiance_std_error.values, reference,
                          im.attrs["batches"], label=f"orthographic {method}")
    assert_consistent(images["forward"].radiance.values,
                      images["forward"].radiance_std_error.values,
                      images["backward"].radiance.values, 32,
                      images["backward"].radiance_std_error.values,
                      label="orthographic forward vs backward")


def test_orthographic_forward_and_backward_agree_on_an_open_box():
    """Forward against backward, the forward paths also with half of their scattering
    directions aimed at the camera (the phase-function lobe about minus its view direction,
    :mod:`cloudct.mc.detector_sampling`), whose weights f / q keep the images unbiased."""
    rng = np.random.default_rng(13)
    axis = 0.05 + 0.1 * np.arange(4)
    medium = optical_medium(axis, axis, axis + 0.5, rng.uniform(0.0, 15.0, (4, 4, 4)),
                            cloud_g=0.5)
    cam = orthographic_camera((0.2, 0.2, 0.7), 25.0, 120.0, width=0.3, nrows=5, distance=2.0)
    scene = Scene([cam], Sun(20.0, 300.0), "open", ground_albedo=0.2)
    backward = render(medium, scene, photons=3_200, method="backward", seed=15,
                      progress=False)
    for aim in (0.0, 0.5):
        forward = render(medium, scene, photons=300_000, seed=14, aim_fraction=aim,
                         progress=False)
        assert forward.attrs["aim_fraction"] == aim
        assert forward.radiance.values.std() > 0.1 * forward.radiance.values.mean()
        assert_consistent(forward.radiance.values, forward.radiance_std_error.values,
                          backward.radiance.values, 32, backward.radiance_std_error.values,
                          label=f"orthographic open box, forward (aim {aim}) vs backward")


def orthographic_gradient_case():
    """A 4x4x4 open box with cloud in every voxel (so that the score function is unbiased
    everywhere), a Lambertian ground, two oblique orthographic cameras and positive pixel
    weights."""
    rng = np.random.default_rng(17)
    axis = 0.05 + 0.1 * np.arange(4)
    medium = optical_medium(axis, axis, axis + 0.5, rng.uniform(2.0, 12.0, (4, 4, 4)),
                            cloud_g=0.6)
    cams = [orthographic_camera((0.2, 0.2, 0.7), zenith, azimuth, width=0.5, nrows=4,
                                distance=2.0)
            for zenith, azimuth in ((30.0, 120.0), (50.0, 10.0))]
    scene = Scene(cams, Sun(20.0, 300.0), "open", ground_albedo=0.2)
    return medium, scene, np.random.default_rng(3).uniform(0.5, 1.5, (2, 4, 4))


def test_orthographic_camera_gradients_agree_with_the_score_function():
    """DRT and sample matching trace camera paths from the image rectangle
    (:func:`~cloudct.mc.cameras.pixel_ray`); the score function differentiates forward
    local estimates projected onto it (:func:`~cloudct.mc.cameras.project`). All 64 voxels
    agree within the standard errors, and the reference resolves the gradient (most
    voxels beyond 4 standard errors from zero)."""
    medium, scene, weights = orthographic_gradient_case()
    score, score_se, _ = score_function_gradient(medium, scene, weights, photons=200_000,
                                                 seed=5, progress=False)
    assert np.sum(np.abs(score) > 4 * score_se) > 40
    for estimate in (drt_gradient, sample_matching_gradient):
        mean, se, _ = estimate(medium, scene, weights, samples_per_pixel=4_096, seed=6)
        assert_consistent(mean, se, score, 32, score_se,
                          label=f"orthographic {estimate.__name__} vs score function")


@pytest.mark.parametrize("storage", ["crossings", "connections"])
def test_orthographic_paths_recycle_exactly_under_the_reference(storage):
    """Stored forward paths with the camera connections of orthographic cameras (stored
    or recomputed), replayed under the medium they were recorded in: the forward render's
    images bitwise and the score-function gradient to rounding."""
    medium, scene, weights = orthographic_gradient_case()
    store = record_paths(medium, scene, photons=20_000, seed=4, storage=storage)
    assert store.storage == storage
    fresh, _ = render_batches(medium, scene, photons=20_000, seed=4, progress=False)
    assert np.array_equal(replay_images(store, medium)[0], fresh)
    replayed = replay_gradient(store, medium, weights)[0]
    score = score_function_gradient(medium, scene, weights, photons=20_000, seed=4,
                                    progress=False)[0]
    scale = np.abs(score).max()
    assert scale > 0.0
    np.testing.assert_allclose(replayed, score, rtol=0.0, atol=1e-12 * scale)


def test_orthographic_projection_follows_the_conventions():
    # looking straight down with +y up: right is +x; row 0 is the top (+y), col 0 the left
    cam = Camera((1.0, 2.0, 5.0), (1.0, 2.0, 0.0), (0.0, 1.0, 0.0), nrows=4, ncols=8,
                 projection="orthographic", width=2.0)
    cams = camera_arrays([cam])
    row, col, dx, dy, dz, inverse_area = project(cams, 0, 1.9, 2.45, 0.3)
    assert (row, col) == (0, 7)
    assert (dx, dy, dz) == (0.0, 0.0, 1.0)  # towards the camera: minus the view direction
    assert np.isclose(inverse_area, 1.0 / 0.25**2)
    assert project(cams, 0, 0.05, 1.55, 0.3)[:2] == (3, 0)
    assert project(cams, 0, 2.1, 2.0, 0.3)[0] == -1  # outside the rectangle
    assert project(cams, 0, 1.0, 2.0, 6.0)[0] == -1  # behind the image plane
    ox, oy, oz, ux, uy, uz = pixel_ray(cams, 0, 0, 7, 0.5, 0.5)
    assert np.allclose((ox, oy, oz, ux, uy, uz), (1.875, 2.375, 5.0, 0.0, 0.0, -1.0))


def test_the_sensor_pass_traces_the_render_paths():
    """The flux tallies leave every path as it was: the sensor kernel's images of an
    orthographic camera are bitwise those of a forward render with the same seed."""
    axis = 0.05 + 0.1 * np.arange(4)
    medium = optical_medium(axis, axis, axis + 0.5,
                            np.random.default_rng(3).uniform(0.0, 10.0, (4, 4, 4)))
    cam = orthographic_camera((0.2, 0.2, 0.7), 30.0, 45.0, width=0.6, nrows=4)
    scene = Scene([cam], Sun(25.0, 10.0), "open", ground_albedo=0.3)
    images, _ = render_batches(medium, scene, photons=2_000, batches=4, seed=5, progress=False)
    k = kernel_inputs(medium, scene)
    sensed = np.zeros((4, 1, 4, 4))
    fluxes = np.zeros((4, 1, 1, NFLUX))
    sensor_batches(k.grid, k.bank, k.cams, k.copies, k.sun, k.periodic, k.ground, 100, 0.95,
                   5, 500, 0, 500, sensed, fluxes, np.zeros(4, np.int64))
    assert np.array_equal(images, sensed / 500)
    # every photon's weight ends somewhere (no path reaches the roulette here)
    kept = fluxes[:, 0, 0, [FLUX_TOP, FLUX_SIDE, FLUX_GROUND, FLUX_MEDIUM]].sum(axis=1)
    assert np.allclose(kept, 500 * k.sun.power, rtol=1e-12)


def test_scene_round_trip_keeps_the_projection(tmp_path):
    ortho = orthographic_camera(CENTRE, 150.0, 30.0, width=0.8, nrows=6, distance=2.0)
    scene = Scene([Camera((0.5, 0.5, 3.0), CENTRE, (0, 1, 0), nrows=6, ncols=6), ortho],
                  Sun(20.0, 45.0), "periodic")
    scene.to_dataset().to_netcdf(tmp_path / "scene.nc")
    loaded = Scene.from_dataset(xr.load_dataset(tmp_path / "scene.nc"))
    assert loaded == scene
    assert [c.projection for c in loaded.cameras] == ["pinhole", "orthographic"]
    old = scene.to_dataset().drop_vars(["projection", "width"]).isel(view=[0])
    assert Scene.from_dataset(old).cameras[0] == scene.cameras[0]  # older files: pinholes
    bad = scene.to_dataset()
    bad["projection"][1] = 7
    with pytest.raises(ValueError, match="projection"):
        Scene.from_dataset(bad)


@pytest.mark.parametrize("kwargs, message", [
    ({"projection": "fisheye"}, "projection"),
    ({"projection": "orthographic"}, "width"),
    ({"projection": "orthographic", "width": -1.0}, "width"),
    ({"width": 1.0}, "only an orthographic"),
])
def test_bad_cameras_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        Camera((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), (0, 1, 0), **kwargs)


def small_medium():
    axis = 0.05 + 0.1 * np.arange(4)
    return optical_medium(axis, axis, axis + 0.5, np.full((4, 4, 4), 5.0))


def test_setups_that_cannot_work_say_so():
    with pytest.raises(ValueError, match="backend"):
        domain_means(small_medium(), backend="tpu")
    with pytest.raises(ValueError, match="probe zenith"):
        domain_means(small_medium(), directions=[(90.0, 0.0)])
    near = orthographic_camera((0.2, 0.2, 0.7), 60.0, 0.0, width=0.6, nrows=4, distance=0.25)
    with pytest.raises(ValueError, match="image plane cuts"):
        render(small_medium(), Scene([near]), photons=100, progress=False)
    slanted = orthographic_camera((0.2, 0.2, 0.7), 80.0, 0.0, width=0.6, nrows=4,
                                  distance=1.0)
    with pytest.raises(ValueError, match="reaches into the periodic slab"):
        render(small_medium(), Scene([slanted], boundary="periodic"), photons=100,
               progress=False)


def test_cli_render_fluxes(tmp_path, capsys):
    save_medium(small_medium(), tmp_path / "medium.nc")
    scene = Scene([Camera((0.2, 0.2, 3.0), (0.2, 0.2, 0.7), (0, 1, 0))], Sun(30.0, 0.0),
                  "periodic", 0.2)
    scene.to_dataset().to_netcdf(tmp_path / "scene.nc")
    out = tmp_path / "fluxes.nc"
    argv = ["render", str(tmp_path / "medium.nc"), "--scene", str(tmp_path / "scene.nc"),
            "--fluxes", "--probe", "0:0", "--probe", "150:90", "-o", str(out),
            "--photons", "3200"]
    assert main(argv) == 0
    assert "albedo" in capsys.readouterr().out
    means = xr.load_dataset(out)
    assert means.radiance.dims == ("direction",)
    assert means.zenith.values.tolist() == [0.0, 150.0]
    assert means.attrs["boundary"] == "periodic" and means.attrs["ground_albedo"] == 0.2
    assert main([*argv, "--overwrite", "--method", "backward"]) == 2
