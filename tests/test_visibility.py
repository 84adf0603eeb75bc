"""Optical distance from the lit and viewed boundary (cloudct.mc.visibility), its split of
epsilon (cloudct.retrieval.metrics.epsilon_by_shell) and the report's table.

The references are analytic and share no code with the kernels: in a uniform box the
optical depth is beta times the distance to where the ray leaves the box (a slab test);
across a medium that varies along x only, beta's integral along x (periodically extended)
over the ray's horizontal run, divided by the direction's x component.
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from cloudct.mc.cameras import Camera
from cloudct.mc.render import render
from cloudct.mc.scene import Scene
from cloudct.mc.sun import Sun
from cloudct.mc.visibility import (
    boundary_optical_distance,
    sun_and_camera_depths,
    voxel_optical_depths,
)
from cloudct.medium import optical_medium
from cloudct.retrieval.metrics import (
    SHELLS,
    epsilon_by_shell,
    epsilon_delta,
    epsilon_split,
    shell_index,
    shell_names,
)
from cloudct.retrieval.report import write_report

NX, NY, NZ = 4, 5, 6
DX, DY, DZ = 0.1, 0.08, 0.05
X0, Y0, Z0 = -0.2, 0.1, 0.5  # the box's lower corner [km]
LO = np.array([X0, Y0, Z0])
HI = LO + [NX * DX, NY * DY, NZ * DZ]


def centres() -> np.ndarray:
    """Voxel centres, float64[nx, ny, nz, 3]."""
    axes = [lo + (np.arange(n) + 0.5) * d for lo, n, d in zip(LO, (NX, NY, NZ), (DX, DY, DZ),
                                                               strict=True)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


def medium(cloud, air=0.0, **kwargs):
    c = centres()
    return optical_medium(c[:, 0, 0, 0], c[0, :, 0, 1], c[0, 0, :, 2],
                          np.broadcast_to(cloud, (NX, NY, NZ)).astype(float),
                          cloud_g=0.85, air_extinction=air, **kwargs)


def exit_distance(origin: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Distance from points inside the box along unit directions u (broadcast, [..., 3])
    to where they leave the box."""
    with np.errstate(divide="ignore"):
        t = np.where(u > 0, (HI - origin) / u, np.where(u < 0, (LO - origin) / u, np.inf))
    return t.min(axis=-1)


def unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def towards_sun(zenith, azimuth):
    th, ph = math.radians(zenith), math.radians(azimuth)
    return np.array([math.sin(th) * math.cos(ph), math.sin(th) * math.sin(ph), math.cos(th)])


def down_camera(x=0.0, y=0.3) -> Camera:
    """An orthographic camera looking straight down from above the box."""
    return Camera((x, y, 3.0), (x, y, 0.0), (0, 1, 0), projection="orthographic", width=1.0)


BETA = 7.0


def test_uniform_box_sun_at_zenith_and_a_camera_straight_above():
    c = centres()
    scene = Scene([down_camera()], Sun(0.0, 0.0))
    sun, cameras = sun_and_camera_depths(medium(BETA), scene)
    expected = BETA * (HI[2] - c[..., 2])
    np.testing.assert_allclose(sun, expected, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(cameras[0], expected, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(boundary_optical_distance(medium(BETA), scene), 2 * expected,
                               rtol=1e-12)


def test_air_does_not_count():
    scene = Scene([down_camera()], Sun(0.0, 0.0))
    with_air = boundary_optical_distance(medium(BETA, air=3.0), scene)
    np.testing.assert_allclose(with_air, 2 * BETA * (HI[2] - centres()[..., 2]), rtol=1e-12)


@pytest.mark.parametrize("zenith, azimuth", [(30.0, 20.0), (55.0, 200.0), (70.0, 300.0)])
def test_uniform_box_oblique_sun(zenith, azimuth):
    c = centres()
    s = towards_sun(zenith, azimuth)
    sun, _ = sun_and_camera_depths(medium(BETA), Scene([down_camera()], Sun(zenith, azimuth)))
    np.testing.assert_allclose(sun, BETA * exit_distance(c, s), rtol=1e-12, atol=1e-12)
    # where the ray stays inside the box up to its top: beta * height / cos(zenith)
    height = HI[2] - c[..., 2]
    top = c[..., :2] + (height / s[2])[..., None] * s[:2]
    inside = np.all((top >= LO[:2]) & (top <= HI[:2]), axis=-1)
    assert inside.any() and (~inside).any()
    np.testing.assert_allclose(sun[inside], BETA * height[inside] / math.cos(math.radians(zenith)),
                               rtol=1e-12)


def test_pinhole_cameras_and_the_nearest_one():
    """Towards a pinhole: along the line to its position; the distance takes the camera
    with the least optical depth, voxel by voxel."""
    c = centres()
    above = (0.0, 0.3, 2.5)
    side = (-1.5, 0.3, 0.65)  # level with the box, on its -x side
    scene = Scene([Camera(above, (0.0, 0.3, 0.6), (0, 1, 0), fov=40.0),
                   Camera(side, (0.0, 0.3, 0.65), (0, 0, 1), fov=40.0)], Sun(0.0, 0.0))
    sun, cameras = sun_and_camera_depths(medium(BETA), scene)
    refs = [BETA * exit_distance(c, unit(np.subtract(p, c))) for p in (above, side)]
    for got, ref in zip(cameras, refs, strict=True):
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)
    nearest = np.minimum(*refs)
    assert (refs[0] < refs[1]).any() and (refs[1] < refs[0]).any()  # each wins somewhere
    np.testing.assert_allclose(boundary_optical_distance(medium(BETA), scene),
                               BETA * (HI[2] - c[..., 2]) + nearest, rtol=1e-12)


def test_orthographic_camera_looks_along_minus_its_view_direction():
    c = centres()
    view = unit([1.0, 0.5, -0.8])
    position = np.array([0.0, 0.3, 0.65]) - 3 * view
    camera = Camera(tuple(position), tuple(position + view), (0, 0, 1),
                    projection="orthographic", width=2.0)
    _, cameras = sun_and_camera_depths(medium(BETA), Scene([camera], Sun(0.0, 0.0)))
    np.testing.assert_allclose(cameras[0], BETA * exit_distance(c, -view), rtol=1e-12,
                               atol=1e-12)


def test_a_single_dense_column_under_non_uniform_levels():
    """One dense column (the rest empty) with z levels of unequal thickness: sun at the
    zenith, tau = beta (z_top - z_centre) in the column, 0 elsewhere; an oblique ray from
    a voxel beside the column crosses it over a known length."""
    edges = Z0 + np.cumsum(np.r_[0.0, 0.02, 0.03, 0.05, 0.07, 0.06, 0.07])
    mid = 0.5 * (edges[:-1] + edges[1:])
    cloud = np.zeros((NX, NY, NZ))
    cloud[2, 3, :] = 40.0
    c = centres()
    m = optical_medium(c[:, 0, 0, 0], c[0, :, 0, 1], mid, cloud, cloud_g=0.85,
                       air_extinction=0.1, z_bounds=np.stack([edges[:-1], edges[1:]], axis=1))
    sun, _ = sun_and_camera_depths(m, Scene([down_camera()], Sun(0.0, 0.0)))
    expected = np.zeros((NX, NY, NZ))
    expected[2, 3, :] = 40.0 * (edges[-1] - mid)
    np.testing.assert_allclose(sun, expected, rtol=1e-12, atol=1e-12)
    # from voxel (1, 3, 0) towards +x at 45 degrees up: the column spans x from X0 + 0.2
    # to X0 + 0.3, crossed over 0.1 / cos(45 deg) while z stays below the top
    sun, _ = sun_and_camera_depths(m, Scene([down_camera()], Sun(45.0, 0.0)))
    assert mid[0] + (X0 + 0.3 - (X0 + 0.15)) < edges[-1]
    np.testing.assert_allclose(sun[1, 3, 0], 40.0 * 0.1 * math.sqrt(2.0), rtol=1e-12)


def _x_integral(profile: np.ndarray, x: np.ndarray) -> np.ndarray:
    """int from X0 to x of the periodically extended beta(x) (NX cells of width DX)."""
    period = NX * DX
    turns = np.floor((x - X0) / period)
    rest = x - X0 - turns * period
    cumulative = np.r_[0.0, np.cumsum(profile * DX)]
    cell = np.minimum((rest // DX).astype(int), NX - 1)
    return turns * cumulative[-1] + cumulative[cell] + profile[cell] * (rest - cell * DX)


@pytest.mark.parametrize("boundary", ["periodic", "open"])
def test_an_oblique_ray_wraps_across_periodic_boundaries(boundary):
    """beta varies along x only; the sun at 75 degrees towards +x: the ray from a voxel
    centre runs (z_top - z) tan(75) in x, several box widths, before it leaves through the
    top (periodic), or leaves through the +x face (open)."""
    profile = np.array([3.0, 0.0, 11.0, 5.0])
    c = centres()
    zenith = 75.0
    s = towards_sun(zenith, 0.0)
    run = (HI[2] - c[..., 2]) * s[0] / s[2]
    if boundary == "periodic":
        assert run.max() > 2 * NX * DX  # the ray wraps (more than twice for the lowest)
        end = c[..., 0] + run
    else:
        end = np.minimum(c[..., 0] + run, HI[0])
    expected = (_x_integral(profile, end) - _x_integral(profile, c[..., 0])) / s[0]
    scene = Scene([down_camera()], Sun(zenith, 0.0), boundary)
    sun, _ = sun_and_camera_depths(medium(profile[:, None, None]), scene)
    np.testing.assert_allclose(sun, expected, rtol=1e-11, atol=1e-11)


def test_a_point_inside_the_box_ends_the_ray_there():
    """The kernel's point targets: the optical depth between the voxel centre and the
    point (beta x distance in a uniform box), 0 at the point itself."""
    from cloudct.mc.visibility import cloud_grid

    c = centres()
    point = c[1, 2, 3]
    depth = voxel_optical_depths(cloud_grid(medium(BETA)), point[None, :].copy(),
                                 np.array([True]), False)[0]
    np.testing.assert_allclose(depth, BETA * np.linalg.norm(c - point, axis=-1), rtol=1e-12,
                               atol=1e-12)


# ----------------------------------------------------------------------------------------
# epsilon by shell
# ----------------------------------------------------------------------------------------


def test_shells_split_epsilon_into_parts_that_sum_to_it():
    rng = np.random.default_rng(5)
    truth = np.where(rng.uniform(size=(6, 7, 8)) < 0.6, rng.uniform(1, 30, (6, 7, 8)), 0.0)
    estimate = np.clip(truth + rng.normal(0, 4, truth.shape), 0, None)
    distance = rng.uniform(0, 12, truth.shape)
    distance[0, 0, 0] = 2.0  # an edge belongs to the shell above it
    parts = epsilon_by_shell(truth, estimate, distance)
    names = shell_names()
    assert names == ["below 2", "2 to 5", "beyond 5"] and SHELLS == (2.0, 5.0)
    assert list(parts) == ["outside"] + [f"{n}{suffix}" for n in names for suffix in
                                         ("", ": true mass", ": retrieved/true")]
    eps = epsilon_delta(truth, estimate)[0]
    assert parts["outside"] + sum(parts[n] for n in names) == pytest.approx(eps, rel=1e-13)
    assert parts["outside"] == pytest.approx(epsilon_split(truth, estimate)["outside"],
                                             rel=1e-13)
    assert sum(parts[f"{n}: true mass"] for n in names) == pytest.approx(1.0, rel=1e-13)
    # by hand, shell by shell
    norm = truth.sum()
    cloud = truth > 0
    for i, (lo, hi) in enumerate([(-np.inf, 2.0), (2.0, 5.0), (5.0, np.inf)]):
        inside = cloud & (distance >= lo) & (distance < hi)
        assert np.array_equal(inside, cloud & (shell_index(distance) == i))
        assert parts[names[i]] == pytest.approx(np.abs(truth - estimate)[inside].sum() / norm,
                                                rel=1e-13)
        assert parts[f"{names[i]}: retrieved/true"] == pytest.approx(
            estimate[inside].sum() / truth[inside].sum(), rel=1e-13)
    # a shell with no cloud has no ratio; other edges, other keys
    empty = epsilon_by_shell(truth, estimate, np.full(truth.shape, 1.0))
    assert empty["beyond 5: true mass"] == 0.0 and math.isnan(empty["beyond 5: retrieved/true"])
    assert list(epsilon_by_shell(truth, estimate, distance, (1.0,))) == [
        "outside", "below 1", "below 1: true mass", "below 1: retrieved/true", "beyond 1",
        "beyond 1: true mass", "beyond 1: retrieved/true"]
    with pytest.raises(ValueError, match="increasing"):
        epsilon_by_shell(truth, estimate, distance, (5.0, 2.0))
    with pytest.raises(ValueError, match="grids differ"):
        epsilon_by_shell(truth, estimate, distance[:-1])


# ----------------------------------------------------------------------------------------
# the report's table
# ----------------------------------------------------------------------------------------


def test_the_report_shows_where_the_error_lives(tmp_path):
    axis = (np.arange(6) + 0.5) * 0.1
    ext = np.zeros((6, 6, 6))
    ext[1:5, 1:5, 1:5] = 2.0
    ext[2:4, 2:4, 2:4] = 25.0  # a dense core: some voxels lie beyond 5
    truth = optical_medium(axis, axis, axis + 0.5, ext, cloud_g=0.85)
    scene = Scene([Camera((0.3, 0.3, 2.5), (0.3, 0.3, 0.8), (0, 1, 0), fov=24.0, nrows=6,
                          ncols=6),
                   Camera((1.6, -0.4, 1.9), (0.3, 0.3, 0.8), (0, 0, 1), fov=28.0, nrows=6,
                          ncols=6)], Sun(35.0, 200.0))
    measurements = render(truth, scene, photons=20_000, seed=3, progress=False)
    result = truth.copy(deep=True)
    result["cloud_extinction"].values = np.where(ext > 0, 8.0, 0.0)
    result["cloud_extinction"].values[0, 0, 0] = 1.5  # outside the true cloud
    summary = write_report(result, tmp_path, truth=truth, measurements=measurements,
                           render_photons=2000).read_text()
    assert (tmp_path / "shells.png").stat().st_size > 1000
    assert "## Where the error lives: by optical distance from the lit and viewed boundary" \
        in summary
    parts = epsilon_by_shell(ext, result["cloud_extinction"].values,
                             boundary_optical_distance(truth, scene))
    eps = epsilon_delta(ext, result["cloud_extinction"].values)[0]
    assert all(parts[f"{n}: true mass"] > 0 for n in shell_names())
    row = re.search(r"\| outside the true cloud \| - \| ([\d.]+)% \| - \|", summary)
    shown = [float(row.group(1))]
    for name in shell_names():
        row = re.search(rf"\| true cloud, d {name} \| ([\d.]+)% \| ([\d.]+)% \| ([\d.]+) \|",
                        summary)
        assert row, name
        assert float(row.group(1)) == pytest.approx(100 * parts[f"{name}: true mass"], abs=0.05)
        assert float(row.group(3)) == pytest.approx(parts[f"{name}: retrieved/true"], abs=0.005)
        shown.append(float(row.group(2)))
    total = float(re.search(r"\| all \| 100.0% \| ([\d.]+)% \|", summary).group(1))
    assert total == pytest.approx(100 * eps, abs=0.05)
    assert f"| last iterate | {eps:.1%} |" in summary
    assert sum(shown) == pytest.approx(total, abs=0.05 * len(shown))  # rounded to 0.1 %
    assert parts["outside"] + sum(parts[n] for n in shell_names()) == pytest.approx(eps,
                                                                                    rel=1e-13)
