"""The matrix of what each gradient estimator supports (cloudct.mc.gradient.ESTIMATORS and
its ``support_table``): the page that shows it is the registry's, and every cell is walked
on a small medium, on the CPU and in this process: a supported combination gives a finite
gradient that is not zero, a refused one stops with its reason and an alternative.

Agreement with references is tested per estimator elsewhere (test_drt.py,
test_sample_matching.py, test_score_gradient.py, test_transmittance_gradient.py,
test_sensors.py for orthographic cameras); the CUDA cells run in test_cuda_sim.py and the
Dask cells in test_distributed.py.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from cloudct.mc.cameras import PROJECTIONS, Camera, orthographic_camera
from cloudct.mc.gradient import ESTIMATORS, gradient_estimate, support_table
from cloudct.mc.scene import Scene
from cloudct.mc.sun import Sun
from cloudct.medium import optical_medium, with_transmittance
from cloudct.physics.transmittance import FAMILIES
from cloudct.retrieval.config import RetrievalConfig

PAGE = Path(__file__).resolve().parents[1] / "docs" / "architecture.md"
#: each family's mode in the walk: the linear mix below 1, where its flight density jumps
MODES = {"exponential": None, "linear-mix": 0.5, "gamma": 2.0}


def test_the_page_shows_the_registrys_table():
    text = PAGE.read_text()
    shown = re.search(r"<!-- support_table: begin -->\n(.*)<!-- support_table: end -->",
                      text, re.S)
    assert shown is not None, "docs/architecture.md lost its support_table markers"
    assert shown.group(1) == support_table(), (
        "docs/architecture.md's table differs from cloudct.mc.gradient.support_table(): "
        "paste the function's output between the markers"
    )


def small_case(projection: str):
    rng = np.random.default_rng(2)
    axis = 0.05 + 0.1 * np.arange(4)
    medium = optical_medium(axis, axis, axis + 0.5, rng.uniform(2.0, 12.0, (4, 4, 4)))
    if projection == "pinhole":
        cam = Camera((0.2, 0.2, 3.0), (0.2, 0.2, 0.7), (0, 1, 0), fov=20.0, nrows=4, ncols=4)
    else:
        cam = orthographic_camera((0.2, 0.2, 0.7), 30.0, 120.0, width=0.5, nrows=4,
                                  distance=2.0)
    residual = rng.uniform(0.5, 1.5, (1, 4, 4))
    return medium, Scene([cam], Sun(20.0, 300.0), "open", 0.2), residual


@pytest.mark.parametrize("projection", PROJECTIONS)
@pytest.mark.parametrize("family", list(FAMILIES))
@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_every_cell_runs_or_is_refused_with_its_reason(name, family, projection):
    record = ESTIMATORS[name]
    medium, scene, residual = small_case(projection)
    if MODES[family] is not None:
        medium = with_transmittance(medium, family, MODES[family])
    assert projection in record.projections
    run = dict(estimator=name, paths=2_000, seed=1, batches=4)
    if family in record.transmittances:
        mean, error, info = gradient_estimate(medium, scene, residual, **run)
        assert np.isfinite(mean).all() and np.isfinite(error).all()
        assert np.abs(mean).max() > 0.0 and info["estimator"] == name
    else:
        with pytest.raises(ValueError, match="not implemented.*(use|is differentiated)"):
            gradient_estimate(medium, scene, residual, **run)


@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_path_recycling_takes_what_records_and_refuses_the_rest(name):
    settings = dict(estimator=(name,), recycling="fixed")
    if ESTIMATORS[name].replayable:
        assert RetrievalConfig(**settings).recycling == "fixed"
    else:
        with pytest.raises(ValueError, match=f"{name!r} does not record: use 'score'"):
            RetrievalConfig(**settings)
