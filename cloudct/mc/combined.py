"""The combined estimator of an image: forward and backward paths joined by multiple
importance sampling.

A path sun -> x_1 -> ... -> x_n -> pixel is sampled by two estimators. The forward one
(:mod:`cloudct.mc.forward`) draws x_1 .. x_n from the sun and connects x_n to the camera by a
local estimate, which carries f(x_n), the phase function at the angle the path turns at
x_n towards the camera; the backward one (:mod:`cloudct.mc.backward`) draws x_n .. x_1 from
the pixel and connects x_1 to the sun by a next-event estimate, which carries f(x_1), the
angle it turns at x_1 coming from the sun. Each samples by the phase function the end the
other only evaluates: where a Mie phase function's diffraction peak (hundreds per sr) falls
on the camera's end, the local estimate is a firefly and the backward path drew that
direction with the peak's own density, and the other way round at the sun's end.

With N_f photons and N_b samples per pixel, the balance heuristic (Veach & Guibas 1995)
gives the path's forward estimate the weight

    w_f = N_f p_f / (N_f p_f + N_b p_b) = D_b / (D_b + (N_b / N_f) D_f),   w_b = 1 - w_f,

where p_f, p_b are the two estimators' densities of the path. Their ratio p_b / p_f is the
forward estimate over the backward estimate of the same path; the albedos and the phase
functions at x_2 .. x_{n-1} (drawn by both, Eq. 33) cancel, which leaves the ends and the
aim factors f / q of each estimator's own draws (:mod:`cloudct.mc.detector_sampling`:
forward directions aimed at the cameras, backward ones at the sun):

    D_f = W T(x_n -> camera) / (r^2 Omega_pixel) c_n  prod_{i < n} (f / q)_i,
    D_b = T(x_1 -> sun) c_1  prod_{i > 1} (f / q_s)_i,

W the total projected area of the sunlit faces (a uniformly entering photon's weight,
:mod:`cloudct.mc.sun`), r^2 Omega_pixel the local estimate's (Eqs. 36-39), c_n the local
estimate's angular factor at x_n (f(x_n) towards the camera, or A cos(theta_camera) / pi at
the ground) and c_1 the next-event estimate's at x_1 (f(x_1) from the sun, A cos(theta0) /
pi at the ground). For a path of one vertex both phase factors are f at the angle between
the sun's rays and the line of sight.

Both estimators compute D_f and D_b of each path they trace from the path alone, so w_f +
w_b = 1 for every path and the sum of the two weighted images is unbiased whatever the
weights' optimality. Where the forward photons enter where the clouds are, a path meets
Russian roulette or bounces off the ground (whose cosine-weighted draws differ between the
two directions), the densities differ from what D_f and D_b assume: the weights stay a
partition of unity (unbiased), no longer exactly the balance heuristic.

The ratio N_b / N_f reaches the kernels as ``CameraArrays.mis_ratio``; 0 (the default)
leaves each estimator alone and unweighted.
"""

from __future__ import annotations

from numba import njit

#: The combined estimator's default backward paths per forward photon: of 1, 4 and 16 with
#: Mie optics, the most efficient on the single cloud and 0.92 of the best (1) on the two
#: cumuli, with the worst view's brightest pixel under 3x its 99th percentile on both
#: (docs/benchmarks.md, "Mie optics").
BACKWARD_PATHS_PER_PHOTON = 4


def samples_per_pixel(photons: int, pixels: int) -> int:
    """Backward samples per pixel for ``photons`` forward photons: :data:`BACKWARD_PATHS_PER_PHOTON`
    paths per photon spread over ``pixels`` pixels (at least 1 per pixel)."""
    return max(1, round(BACKWARD_PATHS_PER_PHOTON * photons / max(int(pixels), 1)))


@njit(cache=True, inline="always")
def forward_share(sun_end, camera_end, ratio):
    """The forward estimate's weight w_f = D_b / (D_b + ratio D_f) (``sun_end`` D_b,
    ``camera_end`` D_f, ``ratio`` N_b / N_f; 0 where both ends are 0: no light there)."""
    total = sun_end + ratio * camera_end
    return sun_end / total if total > 0.0 else 0.0


@njit(cache=True, inline="always")
def backward_share(sun_end, camera_end, ratio):
    """The backward estimate's weight w_b = ratio D_f / (D_b + ratio D_f), 1 - w_f."""
    total = sun_end + ratio * camera_end
    return ratio * camera_end / total if total > 0.0 else 0.0
