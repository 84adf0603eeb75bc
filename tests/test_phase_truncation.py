"""Mie phase functions with their forward peak cut flat (``phase_truncation``,
:mod:`cloudct.optics`, :func:`cloudct.physics.phase.truncated_peak`).

- The cut: within the truncation angle the table is flat at its value there, beyond it
  unchanged, and the share f of scattering it removes equals an independent quadrature of
  the interpolant's peak.
- Delta scaling: the kernels' cloud keeps the scattering outside the peak
  (beta' omega' = beta omega (1 - f)) and the absorption (beta' (1 - omega') =
  beta (1 - omega)); the domain-mean fluxes, which the peak's light hardly moves, agree with
  the full phase functions' within their standard errors.
- The chain rule: with a truncation, the score-function, DRT and recycled gradients are
  gradients with respect to the medium's extinction: they agree with finite differences of
  truncated renders in beta, which the kernels' own gradient (without d beta' / d beta)
  does not.
- The fireflies: renders of the piece with its own droplets, whose plain forward images a
  single peak event outshines (tests/test_detector_sampling.py), stay within twice the
  99th percentile of each view with the peak cut, at several seeds.
- The attribute: checked, refused for Henyey-Greenstein media, kept by netCDF, set by the
  command line.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import xarray as xr
from mcstats import assert_consistent
from scipy import integrate

from cloudct.mc.cameras import Camera
from cloudct.mc.gradient import drt_gradient, score_function_gradient
from cloudct.mc.render import render, render_batches
from cloudct.mc.scene import Scene
from cloudct.mc.sensors import domain_means
from cloudct.mc.sun import Sun
from cloudct.medium import load_medium, microphysical_medium, save_medium
from cloudct.optics import (
    cloud_extinction_scale,
    kernel_arrays,
    to_optical,
    with_phase_truncation,
)
from cloudct.physics.mie import mie_table
from cloudct.physics.phase import truncated_peak
from cloudct.recycling.replay import replay_gradient
from cloudct.recycling.store import record_paths
from data_synth.single_cloud_piece import piece_microphysics, scene_of_piece

CUT = 3.0  # degrees
N = 6
DX = 0.1
BATCHES = 32


# ----------------------------------------------------------------------------------------
# The cut and the scaling
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("reff", [4.0, 10.0, 20.0])
def test_the_cut_is_flat_within_the_angle_and_removes_the_peak_share(reff):
    table = mie_table()
    row = table["phase"].sel(reff=reff, method="nearest").values
    angles = table["scattering_angle"].values
    cut_angles, cut, f = truncated_peak(angles, row, CUT)
    mu = np.cos(np.radians(angles))[::-1]

    def p(m):  # the full table's interpolant, linear in mu
        return np.interp(m, mu, row[::-1])

    p_t = p(math.cos(math.radians(CUT)))
    inside = cut_angles < CUT
    assert np.allclose(cut[inside], p_t) and np.all(row[angles < CUT] >= p_t)
    beyond = cut_angles > CUT
    assert np.array_equal(cut[beyond], row[angles > CUT])
    nodes = np.sort(mu)
    total = sum(integrate.quad(p, a, b)[0] for a, b in zip(nodes[:-1], nodes[1:], strict=True))
    m_t = math.cos(math.radians(CUT))
    peak = integrate.quad(lambda m: p(m) - p_t, m_t, 1.0,
                          points=nodes[nodes > m_t][:-1], limit=400)[0]
    assert f == pytest.approx(peak / total, rel=1e-4)
    assert 0.0 < f < 0.6


def small_mie_medium(cut: float = CUT) -> xr.Dataset:
    """6 x 6 x 6 voxels of 100 m: a dense core (tau ~ 3 per voxel), a thin shell and air."""
    axis = (np.arange(N) + 0.5) * DX
    lwc = np.zeros((N, N, N))
    lwc[1:5, 1:5, 1:5] = 0.02
    lwc[2:4, 2:4, 2:4] = 0.2
    reff = np.where(lwc > 0, 10.0, 0.0)
    reff[1:5, 1:5, 1] = np.where(lwc[1:5, 1:5, 1] > 0, 6.0, 0.0)  # two phase functions
    medium = to_optical(microphysical_medium(axis, axis, axis + 0.5, lwc, reff,
                                             air_extinction=0.8), optics="mie")
    return with_phase_truncation(medium, cut) if cut else medium


def test_delta_scaling_keeps_scattering_outside_the_peak_and_absorption():
    full, cut = small_mie_medium(0.0), small_mie_medium()
    g0, b0 = kernel_arrays(full)
    g1, b1 = kernel_arrays(cut)
    beta, omega = g0.extinction[1], g0.albedo[1]
    beta_c, omega_c = g1.extinction[1], g1.albedo[1]
    cloudy = beta > 0
    angles = full["scattering_angle"].values
    shares = np.array([truncated_peak(angles, r, CUT)[2] for r in full["cloud_phase"].values])
    f = shares[full["cloud_phase_index"].transpose("x", "y", "z").values]
    assert np.allclose(beta_c * omega_c, beta * omega * (1 - f))
    assert np.allclose(beta_c * (1 - omega_c), beta * (1 - omega), rtol=1e-9, atol=1e-15)
    assert np.allclose(cloud_extinction_scale(cut)[cloudy], beta_c[cloudy] / beta[cloudy])
    assert cloud_extinction_scale(full) is None
    assert np.array_equal(g1.extinction[0], g0.extinction[0])  # air untouched
    # the cut bank's largest density is HG-like, the full one's a diffraction peak
    assert b1.table_pdf.max() < 20.0 < 200.0 < b0.table_pdf.max()


def test_fluxes_agree_with_the_full_phase_functions():
    """Albedo and transmittance of the piece (Mie, its own droplets): the peak's light
    goes on almost unscattered, so cutting it leaves the fluxes within their errors."""
    medium = to_optical(piece_microphysics(), optics="mie")
    means = [domain_means(m, photons=1_000_000, seed=3, progress=False)
             for m in (medium, with_phase_truncation(medium, CUT))]
    names = ("albedo", "transmittance")
    full = np.array([float(means[0][n]) for n in names])
    full_se = np.array([float(means[0][n + "_std_error"]) for n in names])
    cut = np.array([float(means[1][n]) for n in names])
    cut_se = np.array([float(means[1][n + "_std_error"]) for n in names])
    assert np.all(full_se < 0.005 * full)  # resolved to 0.5 %
    assert_consistent(cut, cut_se, full, BATCHES, reference_error=full_se,
                      label="fluxes, cut vs full Mie")


# ----------------------------------------------------------------------------------------
# The chain rule
# ----------------------------------------------------------------------------------------


def small_scene() -> Scene:
    c = (0.3, 0.3, 0.8)
    return Scene(
        [Camera((0.3, 0.3, 2.5), c, (0, 1, 0), fov=24.0, nrows=6, ncols=6),
         Camera((1.6, -0.4, 1.9), c, (0, 0, 1), fov=28.0, nrows=6, ncols=6)],
        Sun(zenith=35.0, azimuth=200.0), "open",
    )


def weights() -> np.ndarray:
    return np.random.default_rng(11).uniform(0.5, 1.5, size=(2, 6, 6))


CORE = (slice(2, 4),) * 3  # the dense core's 8 voxels


@pytest.fixture(scope="module")
def cut_core_derivative():
    """dJ/dt of J(t), the core's cloud extinction scaled by 1 + t, at t = 0 (= sum over the
    core of beta_v dJ / d beta_v): central difference with t = +-5 % of truncated renders,
    per batch with common random numbers; mean and standard error."""
    medium = small_mie_medium()
    beta = medium["cloud_extinction"].values[CORE].copy()
    j = []
    for t in (0.05, -0.05):
        m = medium.copy(deep=True)
        m["cloud_extinction"].values[CORE] = beta * (1 + t)
        b, _ = render_batches(m, small_scene(), photons=4_000_000, seed=21, batches=BATCHES,
                              progress=False)
        j.append(np.einsum("bvrc,vrc->b", b, weights()))
    per_batch = (j[0] - j[1]) / 0.1
    return medium, beta, per_batch.mean(), per_batch.std(ddof=1) / math.sqrt(BATCHES)


@pytest.mark.parametrize("estimator", ["score", "drt", "recycled"])
def test_gradients_are_in_the_medium_extinction(cut_core_derivative, estimator):
    """sum over the core of beta_v g_v against the finite difference along the same
    direction. The voxels' estimates share paths, so the sum's standard error is bounded by
    sum beta_v se_v (any correlation) rather than computed: the comparison is conservative
    for agreement, and still has the power to reject the kernels' own gradient (in beta' =
    (1 - omega f) beta: 1.7-1.8x larger here)."""
    medium, beta, fd, fd_se = cut_core_derivative
    if estimator == "score":
        mean, se, _ = score_function_gradient(medium, small_scene(), weights(),
                                              photons=2_000_000, seed=5, progress=False)
    elif estimator == "drt":
        mean, se, _ = drt_gradient(medium, small_scene(), weights(), samples_per_pixel=32768,
                                   seed=5, progress=False)
    else:
        store = record_paths(medium, small_scene(), photons=2_000_000, seed=5,
                             batches=BATCHES)
        mean, se, _ = replay_gradient(store, medium, weights())
    assert fd / fd_se > 8.0  # resolved
    along = np.array([np.sum(beta * mean[CORE])])
    bound = np.array([np.sum(beta * se[CORE])])
    assert_consistent(along, bound, np.array([fd]), BATCHES, reference_error=np.array([fd_se]),
                      label=f"{estimator} vs finite differences, cut Mie")
    scale = cloud_extinction_scale(medium)[CORE]
    own = np.array([np.sum(beta * mean[CORE] / scale)])
    with pytest.raises(AssertionError):
        assert_consistent(own, np.array([np.sum(beta * se[CORE] / scale)]), np.array([fd]),
                          BATCHES, reference_error=np.array([fd_se]), label="kernels' own")


# ----------------------------------------------------------------------------------------
# Fireflies
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_no_firefly_with_the_peak_cut(seed):
    medium = with_phase_truncation(to_optical(piece_microphysics(), optics="mie"), CUT)
    images = render(medium, scene_of_piece(medium), photons=400_000, seed=seed,
                    progress=False)
    assert images.attrs["phase_truncation"] == CUT
    ratio = np.array([im.max() / np.percentile(im, 99) for im in images.radiance.values])
    print(f"seed {seed}: {np.round(ratio, 2)}")
    assert np.all(ratio < 2.0)


# ----------------------------------------------------------------------------------------
# The attribute
# ----------------------------------------------------------------------------------------


def test_the_attribute_is_checked_and_kept(tmp_path):
    medium = small_mie_medium(0.0)
    for bad in (-1.0, 90.0, "three"):
        bad_medium = medium.copy()
        bad_medium.attrs["phase_truncation"] = bad
        with pytest.raises(ValueError, match="phase_truncation"):
            kernel_arrays(bad_medium)
    hg = to_optical(piece_microphysics(), optics="hg")
    with pytest.raises(ValueError, match="Henyey-Greenstein"):
        with_phase_truncation(hg, CUT)
    cut = with_phase_truncation(medium, CUT)
    save_medium(cut, tmp_path / "cut.nc")
    assert load_medium(tmp_path / "cut.nc").attrs["phase_truncation"] == CUT
    assert "phase_truncation" not in with_phase_truncation(cut, 0.0).attrs


def test_render_command_takes_the_truncation(tmp_path):
    from cloudct.cli import main

    path = tmp_path / "medium.nc"
    save_medium(small_mie_medium(0.0), path)
    out = tmp_path / "images.nc"
    assert main(["render", str(path), "-o", str(out), "--photons", "256",
                 "--phase-truncation", "2.5"]) == 0
    assert xr.load_dataset(out).attrs["phase_truncation"] == 2.5


def test_a_retrieval_cuts_the_peak_where_its_settings_say(tmp_path):
    """``phase_truncation`` of the settings cuts the initial medium's peak for the
    retrieval's paths (0 restores the full peak); the result records the cut; Henyey-
    Greenstein media refuse it; out-of-range values are refused before any work."""
    from cloudct.cli import main
    from cloudct.measurements import load_measurements, save_measurements
    from cloudct.retrieval.config import RetrievalConfig
    from cloudct.retrieval.loop import Retrieval

    with pytest.raises(ValueError, match="phase_truncation"):
        RetrievalConfig(phase_truncation=-1.0)
    full = small_mie_medium(0.0)
    save_measurements(render(full, small_scene(), photons=20_000, seed=7, progress=False),
                      tmp_path / "meas.nc")
    save_medium(full, tmp_path / "init.nc")
    measured = load_measurements(tmp_path / "meas.nc")
    cut = Retrieval(measured, full, RetrievalConfig(phase_truncation=CUT))
    assert cut.template.attrs["phase_truncation"] == CUT
    restored = Retrieval(measured, small_mie_medium(), RetrievalConfig(phase_truncation=0.0))
    assert "phase_truncation" not in restored.template.attrs
    kept = Retrieval(measured, small_mie_medium(), RetrievalConfig())
    assert kept.template.attrs["phase_truncation"] == CUT
    hg = to_optical(microphysical_medium(*(full[a].values for a in ("x", "y", "z")),
                                         full["lwc"].values, full["reff"].values), optics="hg")
    with pytest.raises(ValueError, match="Henyey-Greenstein"):
        Retrieval(measured, hg, RetrievalConfig(phase_truncation=CUT))
    out = tmp_path / "result.nc"
    assert main(["retrieve", str(tmp_path / "meas.nc"), "--init", str(tmp_path / "init.nc"),
                 "--iterations", "2", "--photons", "2000", "--phase-truncation", "2.5",
                 "-o", str(out)]) == 0
    assert xr.load_dataset(out).attrs["phase_truncation"] == 2.5
