"""Entry where the clouds are (importance sampling of the sun's entry points, cloudct.mc.sun).

The sunlit faces' grid cells are chosen with p_c = (1 - m) a_c + m a_c g_c / sum a g and the
photons weighted by P a_c / p_c. Checked here:

- m = 0 (the default) is bitwise the uniform source; a medium with no extinction on the
  sun's rays falls back to it; shares outside [0, 1) are refused;
- the cell table: probabilities summing to 1, the projected-area shares of the faces, the
  cloud weights of an overhead sun against column optical depths summed here, weights
  bounded by P / (1 - m) with mean P, and each cell's interval of u giving a point in that
  cell;
- unbiasedness: images (open boundaries with an oblique sun lighting two side faces, and
  periodic ones), the score-function gradient (the proposal is fixed, so it gains no term)
  and the domain fluxes' energy closure with m = 0.7 agree with m = 0 (or 1) within their
  standard errors, on a cloud in one corner of a clear domain (tests/mcstats.py);
- the CUDA kernels under the simulator give bitwise the CPU's per-batch images and
  gradients with m > 0 (one thread per block, the CPU's order of additions).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from mcstats import assert_consistent
from test_cuda_sim import COMPARE, require_numba_cuda, run_script

from cloudct.mc.cameras import Camera
from cloudct.mc.estimate import kernel_inputs
from cloudct.mc.gradient import gradient_estimate, score_function_gradient
from cloudct.mc.render import render, render_batches
from cloudct.mc.scene import Scene
from cloudct.mc.sensors import domain_means
from cloudct.mc.sun import FACE_TOP, FACE_XMAX, FACE_YMAX, Sun, sample_entry_point
from cloudct.medium import optical_medium

N, NZ, DX = 8, 4, 0.1
BATCHES = 32
SHARE = 0.7


def corner_cloud(cloud: float = 20.0, air: float = 0.04):
    """A clear 0.8 x 0.8 x 0.4 km box with a 0.2 x 0.2 x 0.2 km cloud in its (+x, +y)
    corner, the corner that the oblique sun of the open scene lights from the side."""
    axis = DX * (np.arange(N) + 0.5)
    ext = np.zeros((N, N, NZ))
    ext[6:, 6:, 1:3] = cloud
    return optical_medium(axis, axis, 0.5 + DX * (np.arange(NZ) + 0.5), ext,
                          air_extinction=air)


def corner_scenes() -> dict[str, Scene]:
    """Two cameras; open: the sun towards azimuth 30 degrees, so that light also enters
    through the x max and y max faces; periodic: another azimuth, rays wrapping."""
    c = (0.4, 0.4, 0.7)
    cams = [Camera((0.4, 0.4, 3.0), c, (0, 1, 0), fov=18.0, nrows=8, ncols=8),
            Camera((2.0, 1.2, 2.2), c, (0, 0, 1), fov=24.0, nrows=8, ncols=8)]
    return {"open": Scene(cams, Sun(40.0, 30.0), "open", 0.2),
            "periodic": Scene(cams[:1], Sun(30.0, 210.0), "periodic", None)}


def cell_probabilities(sun) -> np.ndarray:
    """p_c of the table of a :class:`~cloudct.mc.sun.SunArrays`."""
    return np.diff(sun.cell_cdf, prepend=0.0)


def test_zero_share_is_the_uniform_source_bitwise():
    medium, scene = corner_cloud(), corner_scenes()["open"]
    assert kernel_inputs(medium, scene).sun.cell_cdf.size == 0
    plain = render(medium, scene, photons=3200, seed=4, progress=False)
    zero = render(medium, scene, photons=3200, seed=4, progress=False, entry_cloud_share=0.0)
    assert np.array_equal(plain.radiance.values, zero.radiance.values)
    assert plain.attrs["entry_cloud_share"] == zero.attrs["entry_cloud_share"] == 0.0


@pytest.mark.parametrize("boundary", ["open", "periodic"])
@pytest.mark.parametrize("share", [0.3, SHARE])
def test_cell_table_shares_and_weights(boundary, share):
    k = kernel_inputs(corner_cloud(), corner_scenes()[boundary], entry_cloud_share=share)
    sun = k.sun
    p = cell_probabilities(sun)
    assert sun.cloud_share == share
    assert np.all(p > 0.0) and math.isclose(p.sum(), 1.0, rel_tol=1e-14)
    assert sun.cell_cdf[-1] == 1.0
    # weights: at most P / (1 - m), mean P; a_c = p_c w_c / P are the projected areas
    assert np.all(sun.cell_weight <= sun.power / (1.0 - share) * (1.0 + 1e-12))
    assert math.isclose(np.dot(p, sun.cell_weight), sun.power, rel_tol=1e-12)
    a = p * sun.cell_weight / sun.power
    faces = np.diff(np.concatenate([[0.0], sun.face_cdf]))
    for face in range(5):
        lo, hi = sun.cell_start[face], sun.cell_start[face + 1]
        assert math.isclose(a[lo:hi].sum(), faces[face], rel_tol=1e-12, abs_tol=1e-15)
    lit = [FACE_TOP, FACE_XMAX, FACE_YMAX] if boundary == "open" else [FACE_TOP]
    counts = np.diff(sun.cell_start)
    assert sorted(np.flatnonzero(counts)) == lit
    assert counts[FACE_TOP] == N * N and sun.cell_start[-1] == p.size


@pytest.mark.parametrize("share", [0.3, SHARE])
def test_overhead_sun_cloud_weights_are_the_columns(share):
    medium = corner_cloud()
    scene = Scene(corner_scenes()["open"].cameras, Sun(0.0, 0.0), "open", None)
    sun = kernel_inputs(medium, scene, entry_cloud_share=share).sun
    assert sun.cell_start[-1] == N * N  # no side face is lit by an overhead sun
    extinction = medium["cloud_extinction"].values + medium["air_extinction"].values
    g = -np.expm1(-extinction.sum(axis=2) * DX).ravel()  # cell (i, j) is i * ny + j
    a = np.full(N * N, 1.0 / (N * N))
    expected = (1.0 - share) * a + share * a * g / np.dot(a, g)
    np.testing.assert_allclose(cell_probabilities(sun), expected, rtol=1e-12)
    np.testing.assert_allclose(sun.cell_weight, sun.power * a / expected, rtol=1e-12)


def test_each_cells_draws_land_in_that_cell():
    k = kernel_inputs(corner_cloud(), corner_scenes()["open"], entry_cloud_share=SHARE)
    sun, grid = k.sun, k.grid
    xe, ye, ze = k.edges
    lower = np.concatenate([[0.0], sun.cell_cdf[:-1]])
    for c in range(sun.cell_cdf.size):
        face = int(np.searchsorted(sun.cell_start, c, side="right")) - 1
        local = c - sun.cell_start[face]
        for u1, u2 in ((0.1, 0.3), (0.9, 0.6)):
            u = 0.5 * (lower[c] + sun.cell_cdf[c])
            x, y, z, weight = sample_entry_point(grid, sun, u, u1, u2)
            assert weight == sun.cell_weight[c]
            if face == FACE_TOP:
                i, j = divmod(local, N)
                assert z == ze[-1] and xe[i] < x < xe[i + 1] and ye[j] < y < ye[j + 1]
            elif face == FACE_XMAX:
                j, kk = divmod(local, NZ)
                assert x == xe[-1] and ye[j] < y < ye[j + 1] and ze[kk] < z < ze[kk + 1]
            else:
                assert face == FACE_YMAX
                i, kk = divmod(local, NZ)
                assert y == ye[-1] and xe[i] < x < xe[i + 1] and ze[kk] < z < ze[kk + 1]


def test_empty_medium_falls_back_to_uniform():
    medium, scene = corner_cloud(cloud=0.0, air=0.0), corner_scenes()["open"]
    sun = kernel_inputs(medium, scene, entry_cloud_share=SHARE).sun
    assert sun.cell_cdf.size == 0 and sun.cloud_share == 0.0
    runs = [render(medium, scene, photons=640, seed=2, progress=False, entry_cloud_share=m)
            for m in (0.0, SHARE)]
    assert np.array_equal(runs[0].radiance.values, runs[1].radiance.values)
    assert runs[1].attrs["entry_cloud_share"] == 0.0


@pytest.mark.parametrize("share", [-0.1, 1.0, 1.5, math.nan, math.inf])
def test_bad_shares_are_refused(share):
    medium, scene = corner_cloud(), corner_scenes()["open"]
    residual = np.ones((2, 8, 8))
    calls = [
        lambda: render(medium, scene, photons=64, progress=False, entry_cloud_share=share),
        lambda: render(medium, scene, photons=64, method="backward", progress=False,
                       entry_cloud_share=share),
        lambda: score_function_gradient(medium, scene, residual, photons=64, progress=False,
                                        entry_cloud_share=share),
        lambda: gradient_estimate(medium, scene, residual, estimator="drt", photons=64,
                                  entry_cloud_share=share),
        lambda: domain_means(medium, photons=64, progress=False, entry_cloud_share=share),
    ]
    for call in calls:
        with pytest.raises(ValueError, match=r"entry_cloud_share must be a finite number in"):
            call()


@pytest.mark.parametrize("boundary", ["open", "periodic"])
def test_images_agree_with_uniform_entry(boundary):
    medium, scene = corner_cloud(), corner_scenes()[boundary]
    runs = []
    for seed, share in ((11, 0.0), (12, SHARE)):
        batches, info = render_batches(medium, scene, photons=160_000, seed=seed,
                                       batches=BATCHES, progress=False,
                                       entry_cloud_share=share)
        assert info["entry_cloud_share"] == share
        runs.append((batches.mean(axis=0), batches.std(axis=0, ddof=1) / math.sqrt(BATCHES),
                     info["events"]))
    (uniform, uniform_se, uniform_events), (cloudy, cloudy_se, cloudy_events) = runs
    seen = (uniform_se > 0.0) | (cloudy_se > 0.0)
    assert seen.sum() > 0.8 * seen.size
    assert_consistent(cloudy[seen], cloudy_se[seen], uniform[seen], BATCHES,
                      reference_error=uniform_se[seen], label=f"entry m={SHARE} {boundary}")
    assert cloudy_events > 2 * uniform_events  # the photons do enter where the cloud is


def test_score_gradient_gains_no_term():
    medium, scene = corner_cloud(), corner_scenes()["open"]
    residual = np.random.default_rng(5).normal(size=(2, 8, 8))
    (g0, se0, _), (g1, se1, info) = (
        score_function_gradient(medium, scene, residual, photons=160_000, seed=seed,
                                batches=BATCHES, progress=False, entry_cloud_share=share)
        for seed, share in ((21, 0.0), (22, SHARE))
    )
    assert info["entry_cloud_share"] == SHARE
    seen = (se0 > 0.0) | (se1 > 0.0)
    assert seen.all()
    assert_consistent(g1, se1, g0, BATCHES, reference_error=se0,
                      label=f"score gradient m={SHARE}")


def test_domain_fluxes_close_with_cloudy_entry():
    medium = corner_cloud()
    kw = dict(sun=Sun(40.0, 30.0), ground_albedo=0.2, photons=64_000, batches=BATCHES,
              progress=False)
    uniform = domain_means(medium, seed=31, **kw)
    cloudy = domain_means(medium, seed=32, entry_cloud_share=SHARE, **kw)
    assert cloudy.attrs["entry_cloud_share"] == SHARE
    assert float(cloudy["incoming_power"]) == float(uniform["incoming_power"])
    names = ["energy_balance", "albedo", "absorptance", "side_escape", "ground_absorptance"]
    assert_consistent(np.array([float(cloudy["energy_balance"])]),
                      np.array([float(cloudy["energy_balance_std_error"])]), 1.0, BATCHES,
                      label="energy closure")
    assert_consistent(np.array([float(cloudy[n]) for n in names]),
                      np.array([float(cloudy[f"{n}_std_error"]) for n in names]),
                      np.array([float(uniform[n]) for n in names]), BATCHES,
                      reference_error=np.array([float(uniform[f"{n}_std_error"])
                                                for n in names]),
                      label="flux shares")


SIMULATOR_SCRIPT = COMPARE + """
import json, sys
import numpy as np
sys.path.insert(0, "tests")
from test_entry_sampling import corner_cloud, corner_scenes
from numba import config
assert config.ENABLE_CUDASIM
import cloudct.mc.cuda_kernels as ck
from cloudct.mc.gradient import score_function_gradient
from cloudct.mc.render import render_batches

ck.THREADS_PER_BLOCK = 1  # threads one after the other: the CPU's order of additions
ck.SORT_PATHS = False
medium, out = corner_cloud(), {}
residual = np.random.default_rng(2).normal(size=(2, 8, 8))
for name, scene in corner_scenes().items():
    runs = [render_batches(medium, scene, photons=96, batches=4, progress=False, backend=b,
                           entry_cloud_share=0.7) for b in ("cpu", "cuda")]
    out[f"render/{name}"] = compare(runs[0][0], runs[1][0])
    out[f"render/{name}"]["info"] = [[r[1][k] for k in ("events", "entry_cloud_share",
                                                        "backend")] for r in runs]
runs = [score_function_gradient(medium, corner_scenes()["open"], residual, photons=96,
                                batches=4, progress=False, backend=b, entry_cloud_share=0.7)
        for b in ("cpu", "cuda")]
out["gradient/open"] = compare(runs[0][0], runs[1][0])
out["gradient/open"]["info"] = [[r[2][k] for k in ("events", "entry_cloud_share", "backend")]
                                for r in runs]
print("RESULT " + json.dumps(out))
"""


def test_cuda_simulator_matches_the_cpu_with_cloudy_entry():
    require_numba_cuda()
    result = run_script(SIMULATOR_SCRIPT, simulator=True)
    assert sorted(result) == ["gradient/open", "render/open", "render/periodic"]
    for key, case in result.items():
        cpu, gpu = case["info"]
        assert case["bitwise"], f"{key}: max difference {case['max_diff']:.3g}"
        assert case["scale"] > 0.0
        assert cpu == [gpu[0], SHARE, "cpu"] and gpu[1:] == [SHARE, "cuda"], (key, cpu, gpu)
