"""Counter-based random streams: one independent stream per photon (or pixel sample).

Each photon's stream is a SplitMix64 sequence started from a state that is a hash of
(seed, photon index). A photon therefore draws the same numbers whatever thread, batch
or device traces it, which makes every render reproducible for a given seed regardless of
the thread count, and lets the CPU and GPU back ends draw identical streams.

The state is a single uint64 passed by value: ``u, state = uniform(state)``. These are
plain ``@njit`` functions, callable from CPU kernels and from numba-cuda kernels.
"""

from __future__ import annotations

import numpy as np
from numba import njit

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_S30 = np.uint64(30)
_S27 = np.uint64(27)
_S31 = np.uint64(31)
_S11 = np.uint64(11)
_TWO_M53 = 1.0 / 9007199254740992.0  # 2**-53

#: Stream domains keep the forward photons, the backward pixel samples and later
#: estimators on disjoint streams for the same seed.
DOMAIN_FORWARD = 1
DOMAIN_BACKWARD = 2
DOMAIN_DRT = 3
DOMAIN_SAMPLE_MATCHING = 4
DOMAIN_PIXEL_TABLE = 5


@njit(cache=True, inline="always")
def mix64(z):
    """The SplitMix64 output function (a bijective 64-bit mixer)."""
    z = (z ^ (z >> _S30)) * _MIX1
    z = (z ^ (z >> _S27)) * _MIX2
    return z ^ (z >> _S31)


@njit(cache=True)
def stream_start(seed, domain, index):
    """Initial state of the stream of sample ``index`` in ``domain`` for ``seed``."""
    key = mix64(np.uint64(seed) * _GOLDEN + np.uint64(domain))
    return mix64(key ^ (np.uint64(index) * _GOLDEN))


@njit(cache=True, inline="always")
def uniform(state):
    """A uniform number in the open interval (0, 1) and the advanced state."""
    state = state + _GOLDEN
    z = mix64(state)
    return ((z >> _S11) + 0.5) * _TWO_M53, state
