"""Space carving: projection and pixel rays (pinhole and orthographic), clear-sky
background, the hull of a known convex blob (open and periodic boundaries, pinhole and
orthographic cameras), the initial medium, the extinction fit, bad input and the ``carve``
command."""

from __future__ import annotations

import numpy as np
import pytest

from cloudct.cli import main
from cloudct.mc.cameras import (
    camera_arrays,
    nine_camera_set,
    orthographic_camera,
    pixel_ray,
    project,
)
from cloudct.mc.render import render, render_batches
from cloudct.mc.scene import Scene
from cloudct.mc.sun import Sun
from cloudct.measurements import save_measurements, synthesize_measurements
from cloudct.medium import cell_edges, load_medium, save_medium, validate_medium
from cloudct.optics import to_optical
from cloudct.retrieval import carving
from cloudct.retrieval.carving import carve, default_k, fit_extinction, initial_medium
from cloudct.retrieval.cloudy_pixels import (
    clear_sky_background,
    pixel_ray_origins,
    pixel_rays,
    project_points,
)
from cloudct.retrieval.metrics import epsilon_delta
from data_synth.synthetic_cloud import blob_cloud, synthetic_cloud


def box_of(medium) -> tuple[np.ndarray, np.ndarray]:
    edges = cell_edges(medium)
    return np.array([e[0] for e in edges]), np.array([e[-1] for e in edges])


@pytest.fixture(scope="module")
def blob():
    """A 0.22 x 0.22 x 0.34 km ellipsoid (20 km-1) in a 0.32 x 0.32 x 0.48 km box."""
    return blob_cloud(16, 16, 12, extinction=20.0)


@pytest.fixture(scope="module")
def blob_measurements(blob):
    """Noise-free images of the blob by the nine cameras (48 x 48 pixels), sun overhead."""
    scene = Scene(nine_camera_set(*box_of(blob), npix=48), Sun(0.0, 0.0))
    return synthesize_measurements(blob, scene, photons=400_000, seed=1, progress=False)


def orthographic_views(target, width: float, npix: int) -> list:
    """Five orthographic cameras 2 km from ``target``: one looking down, four 40 degrees
    from the zenith at azimuths 0, 90, 180 and 270."""
    views = [(0.0, 0.0)] + [(40.0, azimuth) for azimuth in (0.0, 90.0, 180.0, 270.0)]
    return [orthographic_camera(target, zenith, azimuth, width=width, nrows=npix, distance=2.0)
            for zenith, azimuth in views]


def camera_sets() -> dict:
    """Pinhole and orthographic cameras around the box [0, 0.6] x [0, 0.7] x [0, 1]."""
    lo, hi = np.zeros(3), np.array([0.6, 0.7, 1.0])
    return {"pinhole": camera_arrays(nine_camera_set(lo, hi, npix=20)),
            "orthographic": camera_arrays(orthographic_views(0.5 * (lo + hi), 1.2, 20))}


@pytest.mark.parametrize("projection", ["pinhole", "orthographic"])
def test_project_points_is_the_engines_projection(projection):
    cams = camera_sets()[projection]
    points = np.random.default_rng(0).uniform(-0.5, 1.5, size=(2000, 3))
    for view in (0, 3, 4):
        row, col = project_points(cams, view, points)
        expected = np.array([project(cams, view, *p)[:2] for p in points])
        np.testing.assert_array_equal(row, expected[:, 0])
        np.testing.assert_array_equal(col, expected[:, 1])
        assert 0 < np.sum(row >= 0) < len(points)


@pytest.mark.parametrize("projection", ["pinhole", "orthographic"])
def test_pixel_rays_are_the_engines_rays(projection):
    """The carving's rays through 2 x 2 sub-pixel centres are those of the backward
    estimator's :func:`pixel_ray` at the same points of the pixel, to rounding."""
    cams = camera_sets()[projection]
    for view in (0, 3):
        origins, rays = pixel_ray_origins(cams, view, 2), pixel_rays(cams, view, 2)
        assert origins.shape == rays.shape == (20, 20, 4, 3)
        for row, col in ((0, 0), (3, 17), (19, 8)):
            for k, (a, b) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
                ray = pixel_ray(cams, view, row, col, 0.25 + 0.5 * b, 0.25 + 0.5 * a)
                np.testing.assert_allclose(origins[row, col, k], ray[:3], rtol=0, atol=1e-12)
                np.testing.assert_allclose(rays[row, col, k], ray[3:], rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "boundary, ground, photons",
    [("open", None, 2_000_000), ("open", 0.3, 60_000), ("periodic", 0.2, 30_000)],
)
def test_clear_sky_background_matches_an_air_render(blob, boundary, ground, photons):
    """The single-scattering clear-sky background against a Monte Carlo render of the air
    (and ground) alone: per view, the summed radiance agrees to 5 %. The model neglects the
    air's multiple scattering and the ground-air coupling, of the order of the air's optical
    depth (~0.02), and samples each pixel at 4 x 4 points (box edges): it comes out 1-2.5 %
    low. The render's standard error of a view's sum (from its 32 batches) is below 1 %."""
    lo, hi = box_of(blob)
    scene = Scene(nine_camera_set(lo, hi, npix=48), Sun(20.0, 40.0), boundary, ground)
    air = blob.copy()
    air["cloud_extinction"] = air["cloud_extinction"] * 0.0
    batch_sums = render_batches(air, scene, photons=photons, seed=2)[0].sum(axis=(2, 3))
    measured = batch_sums.mean(axis=0)
    std_error = batch_sums.std(axis=0, ddof=1) / np.sqrt(len(batch_sums))
    assert np.all(std_error < 0.01 * measured)
    model = clear_sky_background(scene, blob).sum(axis=(1, 2))
    print(f"{boundary}, ground {ground}: model / render {np.round(model / measured, 3)}")
    np.testing.assert_allclose(model, measured, rtol=0.05)


def hull_against(carved, truth: np.ndarray) -> tuple[np.ndarray, float, float]:
    """The carved hull, the share of the true cloud's voxels it misses, and its
    intersection over union with the true cloud."""
    hull = carved.hull.values.astype(bool)
    return (hull, np.sum(truth & ~hull) / truth.sum(),
            np.sum(truth & hull) / np.sum(truth | hull))


def cloudy_and_silhouette(carved) -> tuple[np.ndarray, np.ndarray]:
    """The cloudy-pixel masks and the hull's silhouettes, per view."""
    return carved.cloud_mask.values.astype(bool), carved.hull_silhouette.values.astype(bool)


def test_carving_recovers_the_blob(blob, blob_measurements):
    """Every blob voxel is in the hull (no false negatives beyond 3 % at the edge) and the
    hull is not much larger than the blob (IoU > 0.6; the nine views lie within 29 degrees
    of the zenith, so the hull is elongated vertically)."""
    truth = blob.cloud_extinction.values > 0
    carved = carve(blob_measurements, blob, fit_photons=None)
    assert carved.attrs["k"] == default_k(9) == 8
    hull, missed, iou = hull_against(carved, truth)
    print(f"blob {truth.sum()} voxels, hull {hull.sum()}, missed {missed:.3f}, IoU {iou:.3f}")
    assert missed <= 0.03
    assert iou > 0.6
    # a stricter vote gives a hull inside this one
    strict = carve(blob_measurements, blob, k=9, fit_photons=None).hull.values.astype(bool)
    assert np.all(hull[strict]) and strict.sum() <= hull.sum()
    # the hull's silhouettes cover the cloudy pixels
    cloudy, silhouette = cloudy_and_silhouette(carved)
    assert np.sum(cloudy & silhouette) >= 0.95 * cloudy.sum() > 0


def test_carving_with_orthographic_cameras_recovers_the_blob(blob):
    """Five orthographic views (32 x 32 pixels, 0.64 km wide, one looking down and four 40
    degrees from the zenith), 200 000 photons: every blob voxel but 3 % at the edge is in
    the hull (measured 2.4 %), IoU > 0.6 (measured 0.70: 754 hull voxels for 552), the
    silhouettes cover the cloudy pixels, and the hull filled at the fitted extinction
    renders as bright as the measurements."""
    scene = Scene(orthographic_views((0.16, 0.16, 0.24), 0.64, 32), Sun(0.0, 0.0))
    measured = synthesize_measurements(blob, scene, photons=200_000, seed=1, progress=False)
    truth = blob.cloud_extinction.values > 0
    carved = carve(measured, blob, fit_photons=20_000)
    hull, missed, iou = hull_against(carved, truth)
    cloudy, silhouette = cloudy_and_silhouette(carved)
    images = render(initial_medium(carved, blob), scene, photons=40_000, seed=7,
                    progress=False)
    ratio = images.radiance.values.sum() / measured.radiance.values.sum()
    print(f"orthographic: blob {truth.sum()} voxels, hull {hull.sum()}, missed {missed:.3f}, "
          f"IoU {iou:.3f}; fitted extinction {carved.attrs['extinction_estimate']:.3g} km-1, "
          f"brightness ratio {ratio:.3f}")
    assert missed <= 0.03 and iou > 0.6
    assert np.sum(cloudy & silhouette) >= 0.95 * cloudy.sum() > 0
    assert ratio == pytest.approx(1.0, abs=0.05)


@pytest.fixture(scope="module")
def wrapped_blob():
    """The blob moved to straddle the x = 0 face (half of it at each side of the box)."""
    wrapped = blob_cloud(16, 16, 12, extinction=20.0)
    wrapped["cloud_extinction"].values = np.roll(wrapped["cloud_extinction"].values, 8, axis=0)
    return wrapped


def test_periodic_carving_recovers_a_blob_across_the_side_faces(wrapped_blob, monkeypatch):
    """Periodic boundaries, the blob across the x = 0 face, the same nine 48 x 48 views and
    400 000 photons as the open test above: every blob voxel is in the hull and IoU > 0.6
    (measured 831 voxels, 0 missed, IoU 0.66; the open test: 840, 0, 0.66). Each view sees
    9 to 25 periodic copies of the box here. Projecting each voxel's own copy only (as
    carving did before) gives a looser hull that holds this one (966 voxels, IoU 0.57).
    The silhouettes, marched across the side faces, cover the cloudy pixels; the profile is
    low in the hull's cloud-free voxels; the fitted extinction renders as bright as the
    measurements."""
    lo, hi = box_of(wrapped_blob)
    scene = Scene(nine_camera_set(lo, hi, npix=48), Sun(0.0, 0.0), "periodic")
    measured = synthesize_measurements(wrapped_blob, scene, photons=400_000, seed=1,
                                       progress=False)
    truth = wrapped_blob.cloud_extinction.values > 0
    carved = carve(measured, wrapped_blob, fit_photons=20_000)
    hull, missed, iou = hull_against(carved, truth)
    cloudy, silhouette = cloudy_and_silhouette(carved)
    profile = carved.extinction_profile.values
    clear, inside = profile[hull & ~truth].mean(), profile[hull & truth].mean()
    print(f"periodic: blob {truth.sum()} voxels, hull {hull.sum()}, missed {missed:.3f}, "
          f"IoU {iou:.3f}; silhouettes cover {np.sum(cloudy & silhouette) / cloudy.sum():.3f} "
          f"of the cloudy pixels; profile {clear:.3f} (cloud-free) {inside:.3f} (blob)")
    assert missed <= 0.03 and iou > 0.6
    assert np.sum(cloudy & silhouette) >= 0.95 * cloudy.sum() > 0
    assert clear < 0.5 * inside

    images = render(initial_medium(carved, wrapped_blob), scene, photons=60_000, seed=7,
                    progress=False)
    ratio = images.radiance.values.sum() / measured.radiance.values.sum()
    print(f"fitted extinction {carved.attrs['extinction_estimate']:.3g} km-1, brightness "
          f"ratio {ratio:.3f}")
    assert ratio == pytest.approx(1.0, abs=0.05)

    monkeypatch.setattr(carving, "view_copies",
                        lambda scene, edges: [np.zeros((1, 3))] * len(scene.cameras))
    own = carve(measured, wrapped_blob, fit_photons=None).hull.values.astype(bool)
    own_iou = np.sum(truth & own) / np.sum(truth | own)
    print(f"own copy only: hull {own.sum()}, IoU {own_iou:.3f}")
    assert np.all(own[hull]) and own.sum() > 1.1 * hull.sum() and own_iou < iou


def test_excess_profile_weighs_the_hull_by_its_faintest_view(blob, blob_measurements):
    """The soft-carving profile: 0 outside the hull, mean 1 in it, lower in the hull's
    cloud-free voxels than in the blob; a masked view does not count; a view that sees no
    cloud light leaves nothing to fill."""
    carved = carve(blob_measurements, blob, fit_photons=None)
    hull = carved.hull.values.astype(bool)
    blob_voxels = blob.cloud_extinction.values > 0
    profile = carved.extinction_profile.values
    assert carved.attrs["profile"] == "excess"
    assert np.all(profile[~hull] == 0.0) and np.all(profile >= 0.0)
    assert profile[hull].mean() == pytest.approx(1.0, rel=1e-12)
    clear, cloudy = profile[hull & ~blob_voxels].mean(), profile[hull & blob_voxels].mean()
    print(f"profile mean: hull's cloud-free voxels {clear:.3f}, blob {cloudy:.3f}")
    assert clear < 0.5 * cloudy
    constant = carve(blob_measurements, blob, profile="constant", fit_photons=None)
    assert np.array_equal(constant.extinction_profile.values, hull.astype(float))

    masked = blob_measurements.copy(deep=True)
    masked["radiance"][4] = np.nan
    eight_views = blob_measurements.isel(view=[0, 1, 2, 3, 5, 6, 7, 8])
    np.testing.assert_allclose(
        carve(masked, blob, k=9, fit_photons=None).extinction_profile.values,
        carve(eight_views, blob, k=8, fit_photons=None).extinction_profile.values,
        rtol=1e-12,
    )
    dark = blob_measurements.copy(deep=True)
    dark["radiance"][4] = carved.clear_sky_radiance.values[4]  # view 4 sees the whole box
    with pytest.raises(ValueError, match="profile is zero"):
        carve(dark, blob, k=8, fit_photons=None)
    with pytest.raises(ValueError, match="profile must be"):
        carve(blob_measurements, blob, profile="gaussian", fit_photons=None)


def test_excess_profile_starts_closer_to_a_structured_cloud():
    """On an LES-style cloud (not the single cloud the default was chosen on), the hull
    filled in the excess profile is closer to the cloud than the constant fill, both at the
    cloud's own mass: epsilon at least a third lower."""
    cloud = to_optical(synthetic_cloud(20, 20, 12, cloud_fraction=0.35, seed=3), wavelength=0.672,
                       optics="mie")
    scene = Scene(nine_camera_set(*box_of(cloud), npix=40), Sun(0.0, 0.0))
    measured = synthesize_measurements(cloud, scene, photons=400_000, seed=2, progress=False)
    truth = cloud.cloud_extinction.values
    eps = {}
    for profile in ("excess", "constant"):
        shape = carve(measured, cloud, profile=profile, fit_photons=None).extinction_profile
        fill = shape.values * truth.sum() / shape.values.sum()
        eps[profile] = epsilon_delta(truth, fill)[0]
    print(f"epsilon at the true mass: {eps}")
    assert eps["excess"] < 2.0 / 3.0 * eps["constant"]


def test_adiabatic_profile_rises_as_an_adiabatic_cloud_above_the_hulls_base(
        blob, blob_measurements):
    """The adiabatic profile is the excess profile times (z - z_base)^(2/3), z_base the
    lower edge of the hull's lowest level: mean 1 in the hull, 0 outside."""
    excess = carve(blob_measurements, blob, fit_photons=None)
    adiabatic = carve(blob_measurements, blob, profile="adiabatic", fit_photons=None)
    hull = excess.hull.values.astype(bool)
    assert np.array_equal(adiabatic.hull.values, excess.hull.values)
    assert adiabatic.attrs["profile"] == "adiabatic"
    z_edges = cell_edges(blob)[2]
    base = z_edges[np.nonzero(hull.any(axis=(0, 1)))[0][0]]
    height = blob.z.values - base
    expected = excess.extinction_profile.values * np.clip(height, 0.0, None) ** (2 / 3)
    expected /= expected[hull].mean()
    np.testing.assert_allclose(adiabatic.extinction_profile.values, expected, rtol=1e-12)
    assert np.all(adiabatic.extinction_profile.values[~hull] == 0.0)


def test_masked_pixels_do_not_carve(blob, blob_measurements):
    masked = blob_measurements.copy(deep=True)
    masked["radiance"][4] = np.nan  # a whole view lost
    carved = carve(masked, blob, k=9, fit_photons=None)
    eight_views = carve(blob_measurements.isel(view=[0, 1, 2, 3, 5, 6, 7, 8]), blob, k=8,
                        fit_photons=None)
    np.testing.assert_array_equal(carved.hull.values, eight_views.hull.values)


@pytest.mark.parametrize("profile", ["excess", "constant", "adiabatic"])
def test_fitted_extinction_reproduces_the_brightness(blob, blob_measurements, profile):
    """The hull filled in the profile at the fitted mean extinction renders (independent
    seed) as bright as the measurements, within 5 %."""
    carved = carve(blob_measurements, blob, profile=profile, fit_photons=40_000)
    beta = carved.attrs["extinction_estimate"]
    initial = initial_medium(carved, blob)
    validate_medium(initial)
    ext = initial.cloud_extinction.values
    hull = carved.hull.values.astype(bool)
    assert np.array_equal(ext, beta * carved.extinction_profile.values)
    assert ext[hull].mean() == pytest.approx(beta, rel=1e-12) and np.all(ext[~hull] == 0.0)
    assert float(initial.cloud_g) == 0.85 and float(initial.air_extinction) == 0.04
    images = render(initial, Scene.from_dataset(blob_measurements), photons=100_000, seed=7,
                    progress=False)
    ratio = images.radiance.values.sum() / blob_measurements.radiance.values.sum()
    print(f"fitted extinction {beta:.3g} km-1 (blob 20, blob total / hull volume "
          f"{blob.cloud_extinction.values.sum() / hull.sum():.3g}); brightness ratio {ratio:.3f}")
    assert ratio == pytest.approx(1.0, abs=0.05)


def test_cameras_that_miss_the_grid_are_refused(blob, blob_measurements):
    far = blob_cloud(16, 16, 12, z_bottom=30.0)
    moved = blob_measurements.copy()
    moved.attrs = {k: v for k, v in moved.attrs.items() if k != "medium_box"}
    with pytest.raises(ValueError, match="does not see"):
        carve(moved, far, fit_photons=None)


def test_template_box_must_match_the_measured_box(blob_measurements):
    other = blob_cloud(16, 16, 10)
    with pytest.raises(ValueError, match="differs from the box"):
        carve(blob_measurements, other, fit_photons=None)
    finer = blob_cloud(32, 32, 24, dx=0.01, dz=0.02)  # same box, finer grid: allowed
    carved = carve(blob_measurements, finer, fit_photons=None)
    assert carved.hull.shape == (32, 32, 24)


def test_initial_medium_refuses_bad_input(blob, blob_measurements):
    carved = carve(blob_measurements, blob, fit_photons=None)
    with pytest.raises(ValueError, match="extinction_estimate"):
        initial_medium(carved, blob)
    with pytest.raises(ValueError, match="differs"):
        initial_medium(carved, blob_cloud(16, 16, 10), 10.0)
    with pytest.raises(ValueError, match="empty"):
        initial_medium(carved.hull * 0, blob, 10.0)
    with pytest.raises(ValueError, match="k must be"):
        carve(blob_measurements, blob, k=10, fit_photons=None)
    # a hull of one voxel cannot be as bright as the blob: the message says why
    tiny = carved.hull * 0
    tiny.values[8, 8, 6] = 1
    with pytest.raises(ValueError, match="hull's 1 voxels are too few"):
        fit_extinction(blob_measurements, tiny, blob, photons=2000, max_iterations=3)


def test_cli_carve(blob, blob_measurements, tmp_path, capsys):
    save_measurements(blob_measurements, tmp_path / "m.nc")
    save_medium(blob, tmp_path / "template.nc")
    argv = ["carve", str(tmp_path / "m.nc"), "-o", str(tmp_path / "init.nc"), "--medium",
            str(tmp_path / "template.nc"), "--extinction", "15", "--figure",
            str(tmp_path / "hull.png")]
    assert main(argv) == 0
    initial = load_medium(tmp_path / "init.nc")
    hull = carve(blob_measurements, blob, fit_photons=None).hull.values > 0
    assert initial.cloud_extinction.values[hull].mean() == pytest.approx(15.0, rel=1e-6)
    assert (tmp_path / "hull.png").stat().st_size > 10_000
    assert "hull of" in capsys.readouterr().out
    assert main(argv) == 2  # refuses to overwrite
    assert main([*argv, "--profile", "constant", "--overwrite"]) == 0
    assert set(np.unique(load_medium(tmp_path / "init.nc").cloud_extinction.values)) == {0, 15}
