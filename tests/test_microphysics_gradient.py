"""Gradients of J = sum_d r_d I_d in every voxel's LWC and r_eff (cloudct.mc.
microphysics_gradient) against central finite differences of the forward model.

The finite differences render the microphysical medium at LWC +- h and r_eff +- h in one
voxel with common random numbers (the same seed on both sides; their standard error from
the same independent batches), through ``to_optical`` and the render kernels, which share
no code with the score terms. r_eff stays inside one interval of the Mie table (the
optics are linear in r_eff there, the derivative is the interval's). In r_eff the
comparison holds the albedo's and the phase function's terms: the test also shows that
the extinction's part alone misses them. The same with the peak cut (a phase truncation,
whose cut share moves with r_eff; the slopes of the cut optics are checked on their own,
deterministically, in test_microphysics_derivatives.py).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from mcstats import assert_consistent
from scipy import stats

from cloudct.mc.cameras import Camera
from cloudct.mc.microphysics_gradient import cloud_reff_slopes, microphysics_gradient
from cloudct.mc.render import render_batches
from cloudct.mc.scene import Scene
from cloudct.mc.sun import Sun
from cloudct.medium import microphysical_medium
from cloudct.optics import peak_shares, to_optical
from cloudct.physics.microphysics import extinction_part_of_gradient
from cloudct.physics.mie import compute_mie_table

N = 5
DX = 0.1
BATCHES = 24
FD_PHOTONS = 960_000
GRAD_PHOTONS = 960_000
#: camera paths of the camera-side estimators (72 pixels)
CAMERA_PATHS = 72 * 2_400
TABLE_REFF = [4.0, 10.0, 16.0, 22.0]
ANGLES = [0.0, 1.0, 2.0, 4.0, 8.0, 15.0, 30.0, 60.0, 90.0, 120.0, 140.0, 160.0, 175.0, 180.0]
#: the voxels compared: dense and thin, in each r_eff interval
VOXELS = [(2, 2, 2), (1, 2, 2), (2, 3, 1), (3, 1, 3), (2, 2, 3)]
#: degrees: at 2.13 micron the cut share f runs from 0.02 (4 micron) to 0.43 (22 micron)
TRUNCATION = 5.0


@pytest.fixture(scope="module")
def table():
    """A coarse Mie table at 2.13 micron, where droplets absorb (the albedo moves with r_eff)."""
    return compute_mie_table(2.13, reff=TABLE_REFF, angles=ANGLES)


@pytest.fixture(scope="module", params=[0.0, TRUNCATION], ids=["full peak", "cut peak"])
def truncation(request):
    return request.param


def medium_of(lwc, reff, truncation=0.0):
    axis = (np.arange(N) + 0.5) * DX
    medium = microphysical_medium(axis, axis, axis + 0.5, lwc, reff, air_extinction=0.3)
    return medium.assign_attrs(phase_truncation=truncation) if truncation else medium


def microphysics():
    """LWC: a cube of 0.05 g m-3 (tau ~ 1 per voxel) with a core of 0.2; r_eff 5-20 micron,
    at least 1 micron from the table's nodes."""
    lwc = np.zeros((N, N, N))
    lwc[1:4, 1:4, 1:4] = 0.05
    lwc[2, 2, 1:4] = 0.2
    rng = np.random.default_rng(3)
    reff = rng.choice([5.5, 7.0, 8.5, 12.5, 14.0, 18.0, 20.5], size=(N, N, N))
    return lwc, reff


def scene():
    c = (0.25, 0.25, 0.75)
    return Scene([Camera((0.25, 0.25, 2.4), c, (0, 1, 0), fov=22.0, nrows=6, ncols=6),
                  Camera((1.5, -0.3, 1.6), c, (0, 0, 1), fov=30.0, nrows=6, ncols=6)],
                 Sun(zenith=30.0, azimuth=210.0), "open")


def pixel_weights():
    return np.random.default_rng(11).uniform(0.5, 1.5, size=(2, 6, 6))


def weighted_batches(lwc, reff, table, seed, truncation):
    optical = to_optical(medium_of(lwc, reff, truncation), table, optics="mie")
    images, _ = render_batches(optical, scene(), photons=FD_PHOTONS, seed=seed,
                               batches=BATCHES, progress=False)
    return np.einsum("bvrc,vrc->b", images, pixel_weights())


def finite_difference(table, name, voxel, h, truncation, seed=21):
    """Per-batch central difference of J in ``name`` ("lwc" or "reff") of one voxel: mean
    and standard error."""
    fields = dict(zip(("lwc", "reff"), microphysics(), strict=True))
    sides = []
    for sign in (1.0, -1.0):
        moved = {k: v.copy() for k, v in fields.items()}
        moved[name][voxel] += sign * h
        sides.append(weighted_batches(moved["lwc"], moved["reff"], table, seed, truncation))
    per_batch = (sides[0] - sides[1]) / (2.0 * h)
    return per_batch.mean(), per_batch.std(ddof=1) / math.sqrt(BATCHES)


#: the finite-difference steps: g m-3 and micron
STEPS = {"lwc": 0.01, "reff": 1.0}


@pytest.fixture(scope="module")
def finite_differences(table, truncation):
    """The finite differences of J at VOXELS (mean, standard error) in ``name``, made once
    per peak and shared by every estimator's test."""
    made = {}

    def of(name):
        if name not in made:
            made[name] = np.array([finite_difference(table, name, v, STEPS[name], truncation)
                                   for v in VOXELS])
        return made[name]

    return of


@pytest.fixture(scope="module")
def gradient(table, truncation):
    return microphysics_gradient(medium_of(*microphysics(), truncation), scene(),
                                 pixel_weights(), photons=GRAD_PHOTONS, mie_table=table,
                                 seed=5, batches=BATCHES, progress=False)


def without(term, estimate, error, fd):
    """The p-value of the finite differences against the estimate less ``term``."""
    gap = fd[:, 0] - (estimate - term)
    chi2 = np.sum(gap**2 / (fd[:, 1] ** 2 + error**2))
    p_value = stats.chi2.sf(chi2, len(VOXELS))
    print(f"without a term: chi2 {chi2:.1f} on {len(VOXELS)} dof, p {p_value:.1e}")
    return p_value


@pytest.mark.parametrize("name", ["lwc", "reff"])
def test_the_score_function_matches_finite_differences(table, truncation, gradient,
                                                       finite_differences, name):
    mean, se, _ = gradient
    fd = finite_differences(name)
    estimate = np.array([mean[name][v] for v in VOXELS])
    error = np.array([se[name][v] for v in VOXELS])
    # the comparison has power: the finite differences are resolved
    assert np.sqrt(np.sum((fd[:, 0] / fd[:, 1]) ** 2)) > 5.0, fd
    assert_consistent(estimate, error, fd[:, 0], BATCHES, reference_error=fd[:, 1],
                      label=f"d/d {name} vs FD")
    if name == "reff":
        assert_vertex_terms_needed(mean, error, fd, table, truncation)


def assert_vertex_terms_needed(mean, error, fd, table, truncation):
    """Without the albedo's and the phase function's terms (d/d r_eff less the extinction's
    part, which d/d LWC gives) the estimate misses the finite differences."""
    lwc, reff = microphysics()
    in_beta = mean["lwc"] / extinction_part_of_gradient(np.ones_like(lwc), lwc, reff, table)[0]
    optical = to_optical(medium_of(lwc, reff, truncation), table, optics="mie")
    beta = optical["cloud_extinction"].transpose("x", "y", "z").values
    cut = in_beta * beta * cloud_reff_slopes(lwc, reff, table, peak_shares(optical))[1]
    extinction = extinction_part_of_gradient(in_beta, lwc, reff, table)[1] + cut
    vertex = np.array([(mean["reff"] - extinction)[v] for v in VOXELS])
    estimate = np.array([mean["reff"][v] for v in VOXELS])
    assert without(vertex, estimate, error, fd) < 1e-3, "the vertex terms are not needed"


@pytest.fixture(scope="module")
def estimator_gradients(table, truncation):
    """d/d LWC and d/d r_eff with every other estimator of d/d beta (the r_eff vertex terms
    from the score function's own pass), made once per peak and estimator."""
    made = {}

    def of(estimator):
        if estimator not in made:
            made[estimator] = microphysics_gradient(
                medium_of(*microphysics(), truncation), scene(), pixel_weights(),
                photons=CAMERA_PATHS if estimator != "combined" else GRAD_PHOTONS // 4,
                mie_table=table, estimator=estimator, seed=9, batches=BATCHES,
                progress=False)
        return made[estimator]

    return of


@pytest.mark.parametrize("estimator", ["drt", "sm", "backward-score", "combined"])
@pytest.mark.parametrize("name", ["lwc", "reff"])
def test_every_estimator_of_the_extinction_gradient_gives_both(
        table, finite_differences, estimator_gradients, estimator, name):
    """d/d LWC = e(r) d/d beta from any estimator of d/d beta, and d/d r_eff from its
    extinction part plus the score function's vertex terms: both match the finite
    differences."""
    mean, se, info = estimator_gradients(estimator)
    assert info["estimator"] == estimator
    fd = finite_differences(name)
    error = np.array([se[name][v] for v in VOXELS])
    assert_consistent(np.array([mean[name][v] for v in VOXELS]), error, fd[:, 0], BATCHES,
                      reference_error=fd[:, 1], label=f"{estimator}: d/d {name} vs FD")


def test_microphysics_gradients_refuse_what_they_do_not_differentiate(table):
    lwc, reff = microphysics()
    optical = to_optical(medium_of(lwc, reff), table, optics="mie")
    with pytest.raises(ValueError, match="microphysical medium"):
        microphysics_gradient(optical, scene(), pixel_weights(), photons=100, mie_table=table)
    with pytest.raises(ValueError, match="estimator must be one of"):
        microphysics_gradient(medium_of(lwc, reff), scene(), pixel_weights(), photons=100,
                              mie_table=table, estimator="fd")


def test_the_cuda_kernels_give_the_cpus_gradients(table, backend):
    """The REFF_GRADIENT pass is one source for both back ends: on the CUDA back end (the
    simulator on CI) both derivatives and their standard errors are the CPU's for the same
    seed, to float64 rounding (the same photons, added in another order)."""
    lwc, reff = microphysics()
    run = dict(photons=96, mie_table=table, seed=7, batches=4)
    mean, error, info = microphysics_gradient(medium_of(lwc, reff), scene(), pixel_weights(),
                                              backend=backend, **run)
    assert info["backend"] == backend
    cpu_mean, cpu_error, _ = microphysics_gradient(medium_of(lwc, reff), scene(),
                                                   pixel_weights(), **run)
    for name in ("lwc", "reff"):
        scale = np.abs(cpu_mean[name]).max()
        assert scale > 0.0 and np.isfinite(mean[name]).all()
        np.testing.assert_allclose(mean[name], cpu_mean[name], rtol=1e-10, atol=1e-12 * scale)
        np.testing.assert_allclose(error[name], cpu_error[name], rtol=1e-8, atol=1e-10 * scale)
