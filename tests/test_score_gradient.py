"""The path-score-function gradient against central finite differences of the forward model.

The quantity is J(beta) = sum_d r_d I_d(beta) for fixed pixel weights r_d, whose gradient
is what a retrieval needs (r_d = residuals, seed paper Eq. 48). Finite differences use
common random numbers (the same seed on both sides), and their standard error comes from
the same independent batches as the images. The medium is 6x6x6 with a dense core, a thin
shell, cloud-free air, and a column with no extinction at all; air is Rayleigh and the cloud
HG, so the phase-ratio term of Eq. (49) is exercised.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from mcstats import assert_consistent

from cloudct.mc.cameras import Camera
from cloudct.mc.gradient import score_function_gradient
from cloudct.mc.render import render_batches
from cloudct.mc.scene import Scene
from cloudct.mc.sun import Sun
from cloudct.medium import optical_medium

N = 6
DX = 0.1
BATCHES = 32
FD_PHOTONS = 1_000_000
GRAD_PHOTONS = 2_000_000


def gradient_medium():
    axis = (np.arange(N) + 0.5) * DX
    ext = np.zeros((N, N, N))
    ext[1:5, 1:5, 1:5] = 2.0  # thin shell, tau ~ 0.2 per voxel
    ext[2:4, 2:4, 2:4] = 25.0  # dense core, tau ~ 2.5 per voxel
    air = np.full((N, N, N), 0.8)
    air[5, :, :] = 0.0  # a slab with no extinction at all
    return optical_medium(
        axis, axis, axis + 0.5, ext, cloud_albedo=0.99, cloud_g=0.7,
        air_extinction=air, air_albedo=0.95,
    )


def gradient_scene():
    c = (0.3, 0.3, 0.8)
    return Scene(
        [
            Camera((0.3, 0.3, 2.5), c, (0, 1, 0), fov=24.0, nrows=6, ncols=6),
            Camera((1.6, -0.4, 1.9), c, (0, 0, 1), fov=28.0, nrows=6, ncols=6),
        ],
        Sun(zenith=35.0, azimuth=200.0),
        "open",
    )


def pixel_weights():
    return np.random.default_rng(11).uniform(0.5, 1.5, size=(2, 6, 6))


def weighted_batches(medium, seed):
    batch_images, _ = render_batches(
        medium, gradient_scene(), photons=FD_PHOTONS, seed=seed, batches=BATCHES,
        progress=False,
    )
    return np.einsum("bvrc,vrc->b", batch_images, pixel_weights())


def with_cloud(medium, voxel, value):
    out = medium.copy(deep=True)
    out["cloud_extinction"].values[voxel] = value
    return out


def finite_difference(medium, voxel, base=None, seed=21):
    """Per-batch derivative of J: central (h = 10% of beta) inside the cloud, the
    second-order one-sided stencil (-3 J0 + 4 J1 - J2) / 2h where beta = 0 (``base``: J0
    of the same seed, if already rendered)."""
    beta = float(medium["cloud_extinction"].values[voxel])
    if beta > 0.0:
        h = 0.1 * beta
        plus = weighted_batches(with_cloud(medium, voxel, beta + h), seed)
        minus = weighted_batches(with_cloud(medium, voxel, beta - h), seed)
        per_batch = (plus - minus) / (2 * h)
    else:
        h = 0.5
        j0 = weighted_batches(medium, seed) if base is None else base
        j1 = weighted_batches(with_cloud(medium, voxel, h), seed)
        j2 = weighted_batches(with_cloud(medium, voxel, 2 * h), seed)
        per_batch = (-3 * j0 + 4 * j1 - j2) / (2 * h)
    return per_batch.mean(), per_batch.std(ddof=1) / math.sqrt(BATCHES)


@pytest.fixture(scope="module")
def score_gradient():
    mean, se, _ = score_function_gradient(
        gradient_medium(), gradient_scene(), pixel_weights(), photons=GRAD_PHOTONS, seed=5,
        batches=BATCHES, progress=False,
    )
    return mean, se


# dense core, thin shell, cloud-free air (cloud extinction 0, air 0.8 /km)
SCATTERING_VOXELS = [(2, 3, 2), (3, 3, 3), (1, 2, 3), (4, 4, 3), (2, 2, 1), (0, 0, 3), (4, 0, 1)]
# no extinction at all (x index 5: air 0 and cloud 0)
EMPTY_VOXELS = [(5, 2, 3), (5, 3, 2), (5, 2, 2)]


def test_score_function_matches_finite_differences(score_gradient):
    """Wherever something scatters (cloud or air), the score function is unbiased: it agrees
    with the finite differences voxel by voxel, including voxels with no cloud."""
    mean, se = score_gradient
    medium = gradient_medium()
    fd = np.array([finite_difference(medium, v) for v in SCATTERING_VOXELS])
    sf = np.array([mean[v] for v in SCATTERING_VOXELS])
    sf_se = np.array([se[v] for v in SCATTERING_VOXELS])
    # the comparison has power: together the finite differences are well resolved
    assert fd[:, 0].sum() / np.sqrt(np.sum(fd[:, 1] ** 2)) > 5.0
    assert_consistent(sf, sf_se, fd[:, 0], BATCHES, reference_error=fd[:, 1], label="SF vs FD")


def test_score_function_misses_in_scattering_where_nothing_scatters(score_gradient):
    """Where the total extinction is zero no path vertex can land, so the score function
    holds only the attenuation term (-l) and misses the light a little cloud would scatter
    in: its estimate lies below the finite difference there, by a significant margin."""
    mean, se = score_gradient
    medium = gradient_medium()
    base = weighted_batches(medium, 21)
    fd = np.array([finite_difference(medium, v, base) for v in EMPTY_VOXELS])
    sf = np.array([mean[v] for v in EMPTY_VOXELS])
    sf_se = np.array([se[v] for v in EMPTY_VOXELS])
    missing = fd[:, 0] - sf
    z = missing.sum() / np.sqrt(np.sum(fd[:, 1] ** 2 + sf_se**2))
    assert z > 4.0, f"expected the missing in-scattering term to show, z = {z:.2f}"
    assert np.all(sf <= 0.0), "with positive weights only attenuation (-l) terms remain there"
