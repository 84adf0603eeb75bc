"""The scene builder (:func:`cloudct.mc.scene.build_scene`, ``cloudct scene``): presets with
the seed paper's numbers (Table 1), a fitted field of view that holds every corner of the
box, overrides, and clear errors for scenes that cannot work."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cloudct.cli import main
from cloudct.mc.scene import build_scene, load_scene

FIELD = (np.zeros(3), np.array([1.58, 1.68, 1.08]))  # the seed paper's cloud-field box


def corners_in_view(camera, lo, hi) -> bool:
    """Every box corner projects inside the image (written from the pinhole model)."""
    forward = np.subtract(camera.lookat, camera.position)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, camera.up)
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    half = math.tan(math.radians(camera.fov) / 2.0)
    for x in (lo[0], hi[0]):
        for y in (lo[1], hi[1]):
            for z in (lo[2], hi[2]):
                d = np.subtract((x, y, z), camera.position)
                depth = d @ forward
                if depth <= 0 or abs(d @ right / depth) > half or abs(d @ up / depth) > half:
                    return False
    return True


@pytest.mark.parametrize("preset, zenith, distance, npix",
                         [("single-cloud", 29.0, 2.0, 76), ("cloud-field", 33.0, 2.16, 86)])
def test_presets_have_the_seed_papers_numbers(preset, zenith, distance, npix):
    lo, hi = FIELD
    scene = build_scene(lo, hi, preset=preset)
    centre = (lo + hi) / 2
    assert len(scene.cameras) == 9
    for i, cam in enumerate(scene.cameras):
        offset = np.subtract(cam.position, centre)
        assert np.linalg.norm(offset) == pytest.approx(distance, rel=1e-12)
        ring_angle = math.degrees(math.acos(offset[2] / np.linalg.norm(offset)))
        assert ring_angle == pytest.approx(0.0 if i == 0 else zenith, abs=1e-9)
        assert (cam.nrows, cam.ncols) == (npix, npix)
        assert np.allclose(cam.lookat, centre)
        assert corners_in_view(cam, lo, hi)
    azimuths = [math.degrees(math.atan2(c.position[1] - centre[1], c.position[0] - centre[0]))
                % 360 for c in scene.cameras[1:]]
    assert np.allclose(azimuths, np.arange(0.0, 360.0, 45.0))
    assert scene.sun.zenith == 0.0 and scene.boundary == "open" and scene.ground_albedo is None


def test_nadir_preset_frames_a_wide_domain():
    lo, hi = np.zeros(3), np.array([6.0, 5.0, 1.5])
    scene = build_scene(lo, hi, preset="nadir")
    assert np.linalg.norm(np.subtract(scene.cameras[0].position, (lo + hi) / 2)) == (
        pytest.approx(1.2 * math.hypot(6.0, 5.0)))
    assert all(corners_in_view(c, lo, hi) for c in scene.cameras)


def test_overrides_and_the_command_line(tmp_path, capsys):
    lo, hi = FIELD
    scene = build_scene(lo, hi, preset="cloud-field", npix=32, fov=70.0, ring_zenith=45.0,
                        sun_zenith=30.0, sun_azimuth=120.0, boundary="periodic",
                        ground_albedo=0.2)
    assert scene.cameras[0].nrows == 32 and scene.cameras[0].fov == 70.0
    assert scene.sun.zenith == 30.0 and scene.sun.azimuth == 120.0
    assert scene.periodic and scene.ground_albedo == 0.2
    out = tmp_path / "scene.nc"
    assert main(["scene", "-o", str(out), "--preset", "cloud-field", "--npix", "40",
                 "--sun-zenith", "20", "--boundary", "periodic", "--ground-albedo", "0.1"]) == 0
    loaded = load_scene(out)
    assert len(loaded.cameras) == 9 and loaded.cameras[4].nrows == 40
    assert loaded.sun.zenith == 20.0 and loaded.periodic and loaded.ground_albedo == 0.1


def test_cameras_at_an_altitude_and_azimuths(tmp_path, capsys):
    lo, hi = FIELD
    scene = build_scene(lo, hi, preset="cloud-field", altitude=4.0, azimuths=[0.0, 120.0, 240.0])
    assert len(scene.cameras) == 4
    assert all(c.position[2] == pytest.approx(4.0) for c in scene.cameras)
    centre = (lo + hi) / 2
    for cam in scene.cameras[1:]:
        offset = np.subtract(cam.position, centre)
        assert math.degrees(math.acos(offset[2] / np.linalg.norm(offset))) == pytest.approx(33.0)
        assert corners_in_view(cam, lo, hi)
    out = tmp_path / "scene.nc"
    assert main(["scene", "-o", str(out), "--altitude", "5", "--azimuths", "10", "190"]) == 0
    assert [round(c.position[2], 9) for c in load_scene(out).cameras] == [5.0, 5.0, 5.0]


@pytest.mark.parametrize("kwargs, message", [
    ({"distance": 0.5}, "farther from the box centre"),
    ({"distance": 1.3}, "too wide to be framed"),
    ({"distance": 3.0, "altitude": 4.0}, "not both"),
    ({"altitude": 1.0}, "not above the box"),
    ({"preset": "satellite"}, "preset must be one of"),
    ({"sun_zenith": 95.0}, "sun"),
    ({"ring_zenith": 120.0, "ground_albedo": 0.3}, "below the ground"),
])
def test_scenes_that_cannot_work_are_refused(kwargs, message):
    lo, hi = FIELD
    with pytest.raises(ValueError, match=message):
        build_scene(lo, hi, **kwargs)


def test_scene_figure(tmp_path, capsys):
    out, figure = tmp_path / "scene.nc", tmp_path / "scene.png"
    assert main(["scene", "-o", str(out), "--preset", "cloud-field", "--sun-zenith", "30",
                 "--figure", str(figure)]) == 0
    assert figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert str(figure) in capsys.readouterr().out


def test_camera_seeing_part_of_a_periodic_field():
    """A nadir camera whose view covers a quarter of a periodic cloud field, and an oblique
    one that sees the field's periodic images beyond its side faces: forward and backward
    estimators agree pixel by pixel."""
    from mcstats import assert_consistent

    from cloudct.mc.cameras import Camera
    from cloudct.mc.render import render
    from cloudct.mc.scene import Scene
    from cloudct.mc.sun import Sun
    from cloudct.medium import optical_medium

    axis = 0.05 + 0.1 * np.arange(8)
    ext = np.random.default_rng(4).uniform(0.0, 15.0, (8, 8, 4))
    medium = optical_medium(axis, axis, 0.05 + 0.1 * np.arange(4), ext, cloud_g=0.7)
    cams = [Camera((0.2, 0.2, 1.5), (0.2, 0.2, 0.2), (0, 1, 0), fov=12.0, nrows=8, ncols=8),
            Camera((1.4, 0.1, 1.0), (0.4, 0.4, 0.2), fov=40.0, nrows=8, ncols=8)]
    scene = Scene(cams, Sun(zenith=25.0, azimuth=40.0), "periodic", ground_albedo=0.2)
    fwd = render(medium, scene, photons=400_000, seed=5, progress=False)
    bwd = render(medium, scene, photons=2048, method="backward", seed=6, progress=False)
    assert_consistent(fwd.radiance.values, fwd.radiance_std_error.values,
                      bwd.radiance.values, fwd.attrs["batches"],
                      reference_error=bwd.radiance_std_error.values,
                      label="part of a periodic field, forward vs backward")


def test_several_rings_and_a_region(tmp_path):
    """Two rings (the second with its own azimuths), aimed at a region of a wide domain:
    the cameras look at the region's centre, the fitted field of view holds the region's
    corners but not the whole domain, and every camera sees the medium."""
    lo, hi = np.zeros(3), np.array([4.0, 4.0, 1.0])
    region = (np.array([0.5, 0.5, 0.0]), np.array([1.5, 1.5, 1.0]))
    scene = build_scene(lo, hi, preset="single-cloud", rings=[(29.0, None), (60.0, [0, 180])],
                        region=region, distance=3.0)
    assert len(scene.cameras) == 1 + 8 + 2
    centre = 0.5 * (region[0] + region[1])
    for cam in scene.cameras:
        assert np.allclose(cam.lookat, centre)
        offset = np.subtract(cam.position, centre)
        assert np.isclose(np.linalg.norm(offset), 3.0)
    zeniths = [math.degrees(math.acos((c.position[2] - centre[2]) / 3.0)) for c in scene.cameras]
    assert np.allclose(sorted(zeniths), [0.0] + [29.0] * 8 + [60.0] * 2)
    far = np.array([4.0, 4.0, 0.0])  # the domain's far corner
    for cam in scene.cameras:
        assert corners_in_view(cam, *region) and not corners_in_view(cam, far, far)
    out = tmp_path / "scene.nc"
    assert main(["scene", "-o", str(out), "--ring", "29", "--ring", "60:0,180", "--region",
                 "0.2", "0.5", "0.2", "0.5", "0.5", "1.0", "--npix", "16"]) == 0
    assert len(load_scene(out).cameras) == 11
    with pytest.raises(ValueError, match="not both"):
        build_scene(lo, hi, rings=[(29.0, None)], ring_zenith=40.0)
    with pytest.raises(ValueError, match="region must be"):
        build_scene(lo, hi, region=(hi, lo))
