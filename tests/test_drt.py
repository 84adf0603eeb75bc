"""Differential ratio tracking (cloudct.mc.drt) against references it shares no code with.

- Its transmittance sampler against an independent chord computation (numpy plane
  crossings): the weight C = int T dt is exact, and the points follow T / C.
- Its gradient against finite differences of the backward renderer, J(beta) = sum_d r_d I_d
  for fixed pixel weights r_d. The finite differences use common random numbers (the same
  seed on both sides) and their standard errors come from the renderer's independent
  batches. The 5x5x5 medium has a dense cloud block (tau 2 per voxel), a thin cloud layer
  above it, cloud-free Rayleigh air, and regions with no extinction at all; the cloud is HG,
  so the mixture terms are exercised, and a Lambertian ground adds ground vertices. One
  camera looks towards the sun's azimuth (forward scattering), one from above.

The same comparison runs under a power-law transmittance (a = 0.5, 2 and inf in bands).

Voxels compared (a fixed selection of each kind; every finite difference costs two or three
renders): dense cloud (1, 1, 2), (1, 3, 2); thin cloud (1, 1, 3); cloud-free air (0, 0, 1),
(4, 0, 2); no extinction at all (0, 1, 4), (0, 2, 3), (4, 0, 4).
"""

from __future__ import annotations

import math
import re

import numpy as np
import pytest
from mcstats import assert_consistent
from numba import njit
from scipy.integrate import quad
from test_transmittance_gradient import mode_field

from cloudct.mc.cameras import Camera
from cloudct.mc.drt import drt_pixel_sample, sample_transmittance
from cloudct.mc.estimate import kernel_inputs
from cloudct.mc.gradient import drt_gradient
from cloudct.mc.random import stream_start
from cloudct.mc.render import render_batches
from cloudct.mc.scene import Scene
from cloudct.mc.sun import Sun
from cloudct.medium import optical_medium, with_transmittance
from cloudct.optics import kernel_arrays
from cloudct.physics.transmittance import GAMMA

N = 5
BATCHES = 32
FD_SAMPLES = 1024  # backward samples per pixel of every finite-difference render
DRT_SAMPLES = 1024  # DRT samples per pixel
CLOUD_VOXELS = [(1, 1, 2), (1, 3, 2), (1, 1, 3)]  # dense (beta 10), dense, thin (beta 1)
AIR_VOXELS = [(0, 0, 1), (4, 0, 2)]  # no cloud, air 0.5 /km
EMPTY_VOXELS = [(0, 1, 4), (0, 2, 3), (4, 0, 4)]  # no extinction at all


def drt_medium():
    axis = (np.arange(N) + 0.5) / N  # 1 km box, 0.2 km voxels
    ext = np.zeros((N, N, N))
    ext[1:4, 1:4, 1:3] = 10.0  # dense block
    ext[1:4, 1:4, 3] = 1.0  # thin layer on top
    ext[2, 2, 2] = 0.0  # a cloud-free hole inside
    air = np.full((N, N, N), 0.5)
    air[0, :, 2:] = 0.0  # no extinction at all (cloud is 0 there too)
    air[4, :, 4] = 0.0
    return optical_medium(
        axis, axis, axis, ext, cloud_albedo=0.99, cloud_g=0.6, air_extinction=air,
        air_albedo=0.912,
    )


def drt_scene(periodic: bool = False, ground: float | None = 0.3):
    target = (0.5, 0.5, 0.5)
    # periodic: cameras must be above the slab
    side = (-1.0, 0.5, 2.2) if periodic else (-2.0, 0.5, 0.8)
    cams = [
        Camera(side, target, (0, 0, 1), fov=30.0, nrows=4, ncols=4),
        Camera((0.6, 0.4, 3.0), target, (0, 1, 0), fov=30.0, nrows=4, ncols=4),
    ]
    boundary = "periodic" if periodic else "open"
    return Scene(cams, Sun(zenith=45.0, azimuth=0.0), boundary, ground)


def pixel_weights():
    return np.random.default_rng(3).uniform(0.5, 1.5, size=(2, 4, 4))


# ----------------------------------------------------------------------------------------
# Finite differences of the backward renderer
# ----------------------------------------------------------------------------------------


def weighted_batches(medium, seed):
    batch_images, _ = render_batches(
        medium, drt_scene(), photons=FD_SAMPLES * BATCHES, method="backward", seed=seed,
        batches=BATCHES, progress=False,
    )
    return np.einsum("bvrc,vrc->b", batch_images, pixel_weights())


def with_cloud(medium, voxel, value):
    out = medium.copy(deep=True)
    out["cloud_extinction"].values[voxel] = value
    return out


def finite_difference(medium, voxel, base, seed):
    """Per-batch derivative of J: central (h = 25% of beta) inside the cloud; the
    second-order one-sided stencil (-3 J0 + 4 J1 - J2) / 2h where the cloud extinction is 0
    (it cannot be negative), with J0 = ``base``. Both stencils err by O(h^2), below 1% of
    the derivative here (checked offline against h / 2 and 2 h at 8x the samples)."""
    beta = float(medium["cloud_extinction"].values[voxel])
    if beta > 0.0:
        h = 0.25 * beta
        plus = weighted_batches(with_cloud(medium, voxel, beta + h), seed)
        minus = weighted_batches(with_cloud(medium, voxel, beta - h), seed)
        per_batch = (plus - minus) / (2 * h)
    else:
        h = 0.4
        j1 = weighted_batches(with_cloud(medium, voxel, h), seed)
        j2 = weighted_batches(with_cloud(medium, voxel, 2 * h), seed)
        per_batch = (-3 * base + 4 * j1 - j2) / (2 * h)
    return per_batch.mean(), per_batch.std(ddof=1) / math.sqrt(BATCHES)


def finite_differences_of_compared_voxels() -> dict:
    """The finite differences of every compared voxel (the ``finite_differences`` fixture
    of conftest.py, shared with the sample-matching tests)."""
    medium = drt_medium()
    seed = 21
    base = weighted_batches(medium, seed)
    voxels = CLOUD_VOXELS + AIR_VOXELS + EMPTY_VOXELS
    return {v: finite_difference(medium, v, base, seed) for v in voxels}


@pytest.fixture(scope="module")
def drt():
    return drt_gradient(
        drt_medium(), drt_scene(), pixel_weights(), samples_per_pixel=DRT_SAMPLES * BATCHES,
        seed=5, batches=BATCHES,
    )


def compare(voxels, drt, finite_differences, label):
    mean, se = drt[:2]
    fd = np.array([finite_differences[v] for v in voxels])
    est = np.array([mean[v] for v in voxels])
    est_se = np.array([se[v] for v in voxels])
    stats = assert_consistent(
        est, est_se, fd[:, 0], BATCHES, reference_error=fd[:, 1], label=label
    )
    for v, e, s, (f, fs) in zip(voxels, est, est_se, fd, strict=True):
        print(f"{label} {v}: estimate {e:+.5f} +- {s:.5f}, FD {f:+.5f} +- {fs:.5f}, "
              f"z = {(e - f) / math.hypot(s, fs):+.2f}")
    print(label, stats)
    return stats


def test_drt_matches_finite_differences_in_cloud(drt, finite_differences):
    compare(CLOUD_VOXELS, drt, finite_differences, "cloud voxels")


def test_drt_matches_finite_differences_in_cloud_free_air(drt, finite_differences):
    compare(AIR_VOXELS, drt, finite_differences, "air voxels")


def test_drt_matches_finite_differences_where_nothing_scatters(drt, finite_differences):
    """Where the total extinction is zero only the DRT samples (t ~ T) can land. There the
    in-scattering term dominates: the derivative is positive and many standard errors
    away from anything an attenuation-only (score-function) estimate could give (<= 0
    with positive weights), so the comparison has the power to see it missing."""
    fd = np.array([finite_differences[v] for v in EMPTY_VOXELS])
    assert np.all(fd[:, 0] / fd[:, 1] > 3.0), fd
    assert fd[:, 0].sum() / np.sqrt(np.sum(fd[:, 1] ** 2)) > 20.0, fd
    compare(EMPTY_VOXELS, drt, finite_differences, "empty voxels")


def test_drt_all_compared_voxels_together(drt, finite_differences):
    stats = compare(
        CLOUD_VOXELS + AIR_VOXELS + EMPTY_VOXELS, drt, finite_differences, "all voxels"
    )
    assert stats["n"] == 8


def test_drt_under_the_power_law_matches_finite_differences():
    """The same eight voxels under a power-law transmittance whose shapes vary (a = 0.5, 2
    and inf in bands, :func:`test_transmittance_gradient.mode_field`), against finite
    differences of the backward renderer under it. Measured when it was written: leaving
    out the hazard of the in-scattering samples, the scale of the segments' deposits or
    that of the sun connections' each fails it (pooled z +5.8, -1.5 with mean z^2 135, and
    -4.9)."""
    medium = drt_medium()
    medium = with_transmittance(medium, "gamma", mode_field("gamma", (N, N, N)))
    seed = 21
    base = weighted_batches(medium, seed)
    voxels = CLOUD_VOXELS + AIR_VOXELS + EMPTY_VOXELS
    fd = {v: finite_difference(medium, v, base, seed) for v in voxels}
    estimate = drt_gradient(medium, drt_scene(), pixel_weights(),
                            samples_per_pixel=DRT_SAMPLES * BATCHES, seed=5, batches=BATCHES)
    assert compare(voxels, estimate, fd, "power law")["n"] == 8


# ----------------------------------------------------------------------------------------
# The transmittance sampler against an independent chord computation
# ----------------------------------------------------------------------------------------


def chord_pieces(grid, p, u, periodic):
    """(t0, t1, ix, iy, iz) of every piece of the ray p + t u inside the medium, from plane
    crossings (numpy; periodic rays unrolled over the horizontal periods)."""
    edges = (grid.x_edges, grid.y_edges, grid.z_edges)
    lo = np.array([e[0] for e in edges])
    hi = np.array([e[-1] for e in edges])
    with np.errstate(divide="ignore"):
        exits = np.where(u > 0, (hi - p) / u, np.where(u < 0, (lo - p) / u, np.inf))
    t_end = exits[2] if periodic else exits.min()
    cuts = [0.0, t_end]
    for a, e in enumerate(edges):
        if u[a] == 0.0:
            continue
        period = e[-1] - e[0]
        shifts = range(-20, 21) if periodic and a < 2 else [0]
        for m in shifts:
            t = (e + m * period - p[a]) / u[a]
            cuts.extend(t[(t > 0.0) & (t < t_end)])
    cuts = np.unique(cuts)
    mid = p + 0.5 * (cuts[:-1] + cuts[1:])[:, None] * u
    index = []
    for a, e in enumerate(edges):
        x = mid[:, a]
        if periodic and a < 2:
            x = e[0] + np.mod(x - e[0], e[-1] - e[0])
        index.append(np.clip(np.searchsorted(e, x) - 1, 0, e.size - 2))
    return cuts[:-1], cuts[1:], index


def transmittance_law(grid, p, u, periodic):
    """C = int T dt, per voxel the probability int_voxel T dt / C, the mean distance
    int t T dt / C, and h(t), the hazard -f'(u) / f(u) at distance t (numpy and scipy's
    quadrature: the exponential, or the power law's closed form f = (1 + m u)^(-1/m) from
    the local optical depth u of every piece, Eq. 7)."""
    t0, t1, (ix, iy, iz) = chord_pieces(grid, p, u, periodic)
    beta = grid.extinction[:, ix, iy, iz].sum(axis=0)
    gamma = grid.transmittance_family[0] == GAMMA
    mode = grid.transmittance_mode[ix, iy, iz] if gamma else np.zeros(beta.size)
    t_in, depth_in = [], []  # T and u (power law) at each piece's entry
    t_now = 1.0
    for b, m, d in zip(beta, mode, t1 - t0, strict=True):
        u_in = (t_now ** -m - 1.0) / m if m > 0 else -math.log(t_now)
        t_in.append(t_now)
        depth_in.append(u_in)
        t_now = (1.0 + m * (u_in + b * d)) ** (-1.0 / m) if m > 0 else t_now * math.exp(-b * d)

    def inside(i, s):  # T at distance s into piece i
        if mode[i] > 0:
            return (1.0 + mode[i] * (depth_in[i] + beta[i] * s)) ** (-1.0 / mode[i])
        return t_in[i] * math.exp(-beta[i] * s)

    pieces = range(beta.size)
    area = np.array([quad(lambda s, i=i: inside(i, s), 0.0, t1[i] - t0[i],
                          epsabs=0.0, epsrel=1e-13)[0] for i in pieces])
    moment = np.array([quad(lambda s, i=i: (t0[i] + s) * inside(i, s), 0.0, t1[i] - t0[i],
                            epsabs=0.0, epsrel=1e-13)[0] for i in pieces])
    c = area.sum()
    prob = np.zeros(grid.extinction.shape[1:])
    np.add.at(prob, (ix, iy, iz), area / c)

    def hazard(t):
        i = np.clip(np.searchsorted(t1, t), 0, beta.size - 1)
        return np.where(mode[i] > 0, 1.0 / (1.0 + mode[i] * (np.array(depth_in)[i]
                                                             + beta[i] * (t - t0[i]))), 1.0)

    return c, prob, moment.sum() / c, hazard

@njit(cache=True)
def _draw(grid, p, u, voxel, periodic, n, seed):
    out_c = np.empty(n)
    out_h = np.empty(n)
    out_t = np.empty(n)
    out_v = np.empty((n, 3), dtype=np.int64)
    for k in range(n):
        state = stream_start(seed, 99, k)
        c, h, qx, qy, qz, ix, iy, iz, state = sample_transmittance(
            grid, p[0], p[1], p[2], u[0], u[1], u[2], voxel[0], voxel[1], voxel[2], periodic,
            state,
        )
        out_c[k] = c
        out_h[k] = h
        out_t[k] = (qx - p[0]) * u[0] + (qy - p[1]) * u[1] + (qz - p[2]) * u[2]
        out_v[k, 0] = ix
        out_v[k, 1] = iy
        out_v[k, 2] = iz
    return out_c, out_h, out_t, out_v


RAYS = [
    # (entry point, direction, periodic): down through the cloud and the empty corner,
    # slanting across it, and a periodic ray that wraps several times
    ((0.1, 0.3, 1.0), (0.3, 0.2, -0.9), False),
    ((0.0, 0.45, 0.7), (0.9, 0.1, -0.2), False),
    ((0.05, 0.2, 1.0), (0.7, 0.6, -0.25), True),
]


@pytest.mark.parametrize("family", ["exponential", "gamma"])
@pytest.mark.parametrize("p, u, periodic", RAYS)
def test_transmittance_sampling_follows_transmittance(p, u, periodic, family):
    """The points follow T / C, with C exact, under the exponential and under a power law
    whose shapes vary along the ray (a = 0.5, 2 and inf), where each point's hazard h is
    that of the closed form at its distance."""
    medium = drt_medium()
    if family == "gamma":
        medium = with_transmittance(medium, "gamma", mode_field("gamma", (N, N, N)))
    grid, _ = kernel_arrays(medium)
    p = np.array(p)
    u = np.array(u) / np.linalg.norm(u)
    edges = (grid.x_edges, grid.y_edges, grid.z_edges)
    voxel = np.array(
        [min(np.searchsorted(e, p[a], side="right") - 1, e.size - 2) for a, e in enumerate(edges)]
    )
    c_ref, prob_ref, mean_t_ref, hazard_ref = transmittance_law(grid, p, u, periodic)
    n = 64_000
    c, h, t, v = _draw(grid, p, u, voxel, periodic, n, 7)
    np.testing.assert_allclose(c, c_ref, rtol=1e-12)  # the weight C is exact
    # voxel frequencies from 32 batches against int_voxel T / C
    batch = np.arange(n) % BATCHES
    counts = np.zeros((BATCHES, *grid.extinction.shape[1:]))
    np.add.at(counts, (batch, v[:, 0], v[:, 1], v[:, 2]), 1.0)
    freq = counts / (n / BATCHES)
    assert not counts[:, prob_ref == 0.0].any(), "a point off the ray's voxels"
    seen = prob_ref > 1e-3
    assert prob_ref[seen].sum() > 0.99 and seen.sum() >= 5
    assert_consistent(
        freq.mean(axis=0)[seen], freq.std(axis=0, ddof=1)[seen] / math.sqrt(BATCHES),
        prob_ref[seen], BATCHES, label="voxel frequencies",
    )
    if periodic:  # (a wrapped point's distance is not its offset from the start)
        return
    assert_consistent(  # distances along the ray: mean against int t T dt / C
        np.array([t.mean()]), np.array([t.std(ddof=1) / math.sqrt(n)]),
        np.array([mean_t_ref]), n, label="mean distance",
    )
    np.testing.assert_allclose(h, hazard_ref(t), rtol=1e-12)
    assert (family == "gamma") == bool(np.any(h < 0.99))  # the power law's h is tested


# ----------------------------------------------------------------------------------------
# API
# ----------------------------------------------------------------------------------------


def test_drt_gradient_is_linear_in_the_residual_and_checks_its_shape():
    medium, scene = drt_medium(), drt_scene(periodic=True, ground=None)
    r = pixel_weights()
    g1, s1, _ = drt_gradient(medium, scene, r, samples_per_pixel=64, seed=2, batches=4)
    g2, s2, _ = drt_gradient(medium, scene, 2.0 * r, samples_per_pixel=64, seed=2, batches=4)
    assert np.any(g1 != 0.0)
    np.testing.assert_array_equal(g2, 2.0 * g1)
    np.testing.assert_array_equal(s2, 2.0 * s1)
    g0, s0, _ = drt_gradient(medium, scene, np.zeros_like(r), samples_per_pixel=8, batches=2)
    assert not g0.any() and not s0.any()
    with pytest.raises(ValueError, match="residual"):
        drt_gradient(medium, scene, r[:1], samples_per_pixel=8, batches=2)
    with pytest.raises(ValueError, match="residual"):
        drt_gradient(medium, scene, np.full_like(r, np.nan), samples_per_pixel=8, batches=2)


# ----------------------------------------------------------------------------------------
# Speed
# ----------------------------------------------------------------------------------------


def test_a_drt_sample_updates_no_reference_counts():
    """DRT's routines, and the walk, camera and physics routines they call, are compiled
    without numba's reference counting (``_nrt=False``, docs/architecture.md). With it, every
    call increments and decrements the count of each array the routine receives, about 30
    atomic updates each way for a routine that takes the grid, the phase bank, the cameras
    and the sun: a third of DRT's time on the CPU. The LLVM IR of a pixel sample, with every
    routine it calls linked in, updates no count."""
    k = kernel_inputs(drt_medium(), drt_scene(), aim_fraction=0.0)

    @njit(_nrt=False)
    def one_sample(grid, bank, cams, sun, periodic, ground_albedo, gradient):
        return drt_pixel_sample(grid, bank, cams, sun, periodic, ground_albedo, 100, 0.95, 1,
                                0, 1, 1, 1, 1.0, gradient, 1.0)

    gradient = np.zeros(k.grid.extinction.shape[1:])
    one_sample(k.grid, k.bank, k.cams, k.sun, k.periodic, k.ground, gradient)
    ir = one_sample.inspect_llvm(one_sample.signatures[0])
    functions = {m.group(1): m.group(0) for m in re.finditer(
        r'^define [^\n]*?@"?([^\s("]+)"?\(.*?^\}', ir, re.M | re.S)}
    routines = [name for name in functions if name.startswith("_ZN7cloudct")]
    for routine in ("drt_pixel_sample", "trace_path", "sample_transmittance", "march",
                    "camera_ray_entry"):
        assert any(routine in name for name in routines), f"{routine} not linked in"
    counting = [name for name in routines
                if "@NRT_incref(" in functions[name] or "@NRT_decref(" in functions[name]]
    assert not counting, f"reference counts updated in {counting}"
