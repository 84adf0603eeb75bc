"""Fixtures shared by several test modules, and the order in which the files run."""

from __future__ import annotations

import pytest

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


@pytest.fixture(scope="session")
def finite_differences() -> dict:
    """Finite differences of the backward renderer on the DRT test medium (test_drt.py),
    for the voxels that the DRT and sample-matching tests compare: computed once."""
    from test_drt import finite_differences_of_compared_voxels

    return finite_differences_of_compared_voxels()
