"""Fixtures shared by several test modules."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def finite_differences() -> dict:
    """Finite differences of the backward renderer on the DRT test medium (test_drt.py),
    for the voxels that the DRT and sample-matching tests compare: computed once."""
    from test_drt import finite_differences_of_compared_voxels

    return finite_differences_of_compared_voxels()
