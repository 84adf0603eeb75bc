"""Fixtures shared by several test modules, and the order in which the files run.

The ``backend`` fixture runs a test on each compute back end, ``"cpu"`` and ``"cuda"``
(PySDM's habit of a fake GPU back end, so that the GPU code paths run on CI): where no GPU
is usable, a test's ``"cuda"`` case runs again in a new pytest process with numba-cuda's
simulator switched on (``NUMBA_ENABLE_CUDASIM=1`` must be set before numba is imported, so
it cannot be switched on in this process), and passes or fails as it does there; on a
machine with a GPU it runs here, on the GPU.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# retrieve and demo compile their kernels ahead in other processes (cloudct.retrieval.warm_up);
# the suite's processes compile theirs as they go, and test_warm_up.py turns it on
os.environ.setdefault("CLOUDCT_COMPILE_AHEAD", "0")

#: The test files that take longest on 2 cores (minutes each), longest first. They run
#: before the others so that the README's parallel run (one file per worker,
#: ``--dist loadfile``) does not end with one worker on a long file while the other idles.
LONGEST_FIRST = (
    "test_cuda_ptx.py", "test_cuda_sim.py", "test_retrieval.py", "test_recycling.py",
    "test_cloud_field.py", "test_drt.py", "test_detector_sampling.py", "test_docs.py",
    "test_distributed.py", "test_sample_matching.py",
)


def pytest_configure(config) -> None:
    """Keep the order of :func:`pytest_collection_modifyitems` under pytest-xdist, whose
    default (``--loadscope-reorder``) would start the files with the most tests first."""
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(config, items) -> None:
    """Run the files of :data:`LONGEST_FIRST` first, in that order; the rest follow in
    their collected order (a stable sort keeps every file's own order)."""
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


@pytest.fixture(params=["cpu", "cuda"])
def backend(request) -> str:
    """The back end a test runs its estimates on: each test that takes it runs twice."""
    return request.param


def _in_the_simulator(item) -> bool:
    """Whether ``item`` is a ``backend="cuda"`` case that must run in the simulator."""
    callspec = getattr(item, "callspec", None)
    if callspec is None or callspec.params.get("backend") != "cuda":
        return False
    from numba import config

    if config.ENABLE_CUDASIM:
        return False  # this process is the simulator's
    from cloudct.mc.backend import cuda_unavailable_reason

    return cuda_unavailable_reason() is not None


@pytest.hookimpl(tryfirst=True)
def pytest_pyfunc_call(pyfuncitem) -> bool | None:
    """Run a ``backend="cuda"`` case in numba-cuda's simulator, in a new process, where no
    GPU is usable here (the module docstring)."""
    if not _in_the_simulator(pyfuncitem):
        return None
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", pyfuncitem.nodeid],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=900,
    )
    summary = proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else ""
    assert proc.returncode == 0 and re.match(r"1 passed\b", summary), (
        f"{pyfuncitem.nodeid} failed in the CUDA simulator (rc {proc.returncode}):\n"
        f"{proc.stdout[-6000:]}\n{proc.stderr[-3000:]}"
    )
    return True


@pytest.fixture(scope="session")
def finite_differences() -> dict:
    """Finite differences of the backward renderer on the DRT test medium (test_drt.py),
    for the voxels that the DRT and sample-matching tests compare: computed once."""
    from test_drt import finite_differences_of_compared_voxels

    return finite_differences_of_compared_voxels()
