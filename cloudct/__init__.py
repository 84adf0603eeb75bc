"""cloudct: 3D cloud tomography by differentiable Monte Carlo radiative transfer."""

from cloudct.jit_cache import install_cpu_locator

__version__ = "0.1.0"

# before any cloudct function is compiled: cache compiled kernels where a change to a
# routine they call invalidates them (cloudct.jit_cache)
install_cpu_locator()
