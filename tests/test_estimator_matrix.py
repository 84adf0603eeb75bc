"""The matrix of what each gradient estimator supports (cloudct.mc.gradient.ESTIMATORS and
its ``support_table``) and the batch kernels that trace them (cloudct.mc.estimate.
BATCH_KERNELS): the pages that show them are the registries', and every cell is walked on
a small medium: a supported combination gives a finite gradient that is not zero (on the
CUDA back end, through the ``backend`` fixture of conftest.py: the CPU's, to rounding), a
refused one stops with its reason and an alternative. Every estimator also runs through
the executors' one entry point (``batch_sums`` by kernel name), bitwise as in this
process.

Agreement with references is tested per estimator elsewhere (test_drt.py,
test_sample_matching.py, test_score_gradient.py, test_transmittance_gradient.py,
test_sensors.py for orthographic cameras); the CUDA kernels' finer checks (bitwise with
one thread per block, the replays) in test_cuda_sim.py and the Dask cells in
test_distributed.py.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from cloudct.mc.cameras import PROJECTIONS, Camera, orthographic_camera
from cloudct.mc.estimate import BATCH_KERNELS, BY_VIEWS, Sampling, batch_kernel_table
from cloudct.mc.gradient import ESTIMATORS, gradient_estimate, support_table
from cloudct.mc.render import render_batches
from cloudct.mc.scene import Scene
from cloudct.mc.sun import Sun
from cloudct.medium import optical_medium, with_transmittance
from cloudct.physics.transmittance import FAMILIES
from cloudct.recycling import replay  # noqa: F401  (registers the replay kernels the page shows)
from cloudct.retrieval.config import RetrievalConfig

PAGE = Path(__file__).resolve().parents[1] / "docs" / "architecture.md"
#: each family's mode in the walk: the linear mix below 1, where its flight density jumps
#: a refusal names what is not implemented and the alternative
REFUSED = "not implemented.*(use|is differentiated)"
MODES = {"exponential": None, "linear-mix": 0.5, "gamma": 2.0}


@pytest.mark.parametrize("table", [support_table, batch_kernel_table])
def test_the_page_shows_the_registrys_table(table):
    name = table.__name__
    text = PAGE.read_text()
    shown = re.search(rf"<!-- {name}: begin -->\n(.*)<!-- {name}: end -->", text, re.S)
    assert shown is not None, f"docs/architecture.md lost its {name} markers"
    assert shown.group(1) == table(), (
        f"docs/architecture.md's table differs from {table.__module__}.{name}(): paste the "
        "function's output between the markers"
    )


class InProcessExecutor:
    """The smallest BatchExecutor: its one entry point runs any batch kernel by name here,
    through the runner of the kernel's record, in one call per batch range of two batches
    (as a worker would, with the sample range shifted)."""

    def __init__(self):
        self.kernels = []

    def batch_sums(self, kernel, k, args, *, per_batch, sampling, progress, desc):
        from cloudct.distributed.batches import assemble, batch_task

        self.kernels.append(kernel)
        if BATCH_KERNELS[kernel].split(args) == BY_VIEWS:
            nview = k.cams.position.shape[0]
            parts = [batch_task(kernel, k, sampling, per_batch, args, v, 1)
                     for v in range(nview)]
            values, parts = assemble(parts, nview, axis=1)
            events = np.sum([p.events for p in parts], axis=0)
        else:
            parts = [batch_task(kernel, k, sampling, per_batch, args, b, 2)
                     for b in range(0, sampling.batches, 2)]
            values, parts = assemble(parts, sampling.batches)
            events = np.concatenate([p.events for p in parts])
        return values, events, {"wall_time": 0.0, "backend": "cpu"}


@pytest.mark.parametrize("estimator", ["render-forward", "render-backward", *ESTIMATORS])
def test_one_executor_entry_point_serves_every_estimator_bitwise(estimator):
    medium, scene, residual = small_case("pinhole")
    ex = InProcessExecutor()
    if estimator.startswith("render"):
        run = dict(photons=512, seed=3, batches=4, method=estimator.split("-")[1],
                   progress=False)
        ref, _ = render_batches(medium, scene, **run)
        out, info = render_batches(medium, scene, executor=ex, **run)
    else:
        run = dict(estimator=estimator, photons=1_024, seed=3, batches=4,
                   pixel_sampling="residual" if estimator == "drt" else "uniform")
        ref = gradient_estimate(medium, scene, residual, **run)[:2]
        *out, info = gradient_estimate(medium, scene, residual, executor=ex, **run)
    # the combined gradient traces two kernels (forward photons, camera paths)
    assert len(ex.kernels) == (2 if estimator == "combined" else 1)
    assert all(kernel in BATCH_KERNELS for kernel in ex.kernels)
    assert np.array_equal(np.asarray(out), np.asarray(ref)) and info["events"] > 0


def test_a_repeated_call_compiles_nothing():
    """Each estimator and render, called a second time with the same kinds of arguments,
    runs its compiled kernels without entering the compiler: a kernel that asks for a
    literal argument (``numba.literally``) re-runs numba's front end on every call before
    it finds its specialisation (found 2026-11-28: 0.12 s per batch round, 6 s per
    iteration of the tiny retrieval)."""
    from numba.core import event

    medium, scene, residual = small_case("pinhole")
    calls = {e: (lambda e=e: gradient_estimate(medium, scene, residual, estimator=e,
                                               photons=256, seed=1, batches=2))
             for e in ESTIMATORS}
    for method in ("forward", "backward"):
        calls[f"render-{method}"] = lambda method=method: render_batches(
            medium, scene, photons=256, seed=1, batches=2, method=method, progress=False)
    for call in calls.values():
        call()  # compiled (or loaded from the cache) here
    compiled = []

    class Listener(event.Listener):
        def on_start(self, ev):
            compiled.append(str(ev.data.get("dispatcher", ev.data)))

        def on_end(self, ev):
            pass

    for name, call in calls.items():
        with event.install_listener("numba:compile", Listener()):
            call()
        assert not compiled, f"{name}: a repeated call compiled {compiled}"


def test_sampling_refuses_what_cannot_work():
    assert Sampling().per_batch(65) == 3  # 32 batches: rounded up
    for bad, match in (({"batches": 1}, "batches must be at least 2"),
                       ({"rr_survival": 0.0}, "rr_survival"), ({"rr_depth": 0}, "rr_depth"),
                       ({"backend": "gpu"}, "backend must be one of")):
        with pytest.raises(ValueError, match=match):
            Sampling(**bad)
    with pytest.raises(ValueError, match="positive count"):
        Sampling().per_batch(0)


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


def test_the_matrix_on_each_back_end(backend):
    """Every cell of the matrix (estimator x transmittance x camera) on ``backend``: on the
    CPU each supported cell gives a finite, non-zero gradient; on the CUDA back end (the
    simulator on CI) each gives the CPU's gradient and standard error for the same seed, to
    float64 rounding (the same photons, added in another order); a refused cell stops there
    with its reason too."""
    assert backend in ESTIMATORS["score"].backends
    run = dict(photons=600, seed=4, batches=4)
    for name, record in ESTIMATORS.items():
        for family in FAMILIES:
            for projection in PROJECTIONS:
                medium, scene, residual = small_case(projection)
                if MODES[family] is not None:
                    medium = with_transmittance(medium, family, MODES[family])
                cell = f"{name}, {family}, {projection}"
                assert projection in record.projections, cell
                if family not in record.transmittances:
                    with pytest.raises(ValueError, match=REFUSED):
                        gradient_estimate(medium, scene, residual, estimator=name,
                                          backend=backend, **run)
                    continue
                mean, error, info = gradient_estimate(medium, scene, residual, estimator=name,
                                                      backend=backend, **run)
                assert info["backend"] == backend and info["estimator"] == name, cell
                assert np.isfinite(mean).all() and np.isfinite(error).all(), cell
                assert np.abs(mean).max() > 0.0, cell
                if backend != "cpu":
                    cpu_mean, cpu_error, _ = gradient_estimate(medium, scene, residual,
                                                               estimator=name, **run)
                    scale = np.abs(cpu_mean).max()
                    np.testing.assert_allclose(mean, cpu_mean, rtol=1e-10, atol=1e-12 * scale,
                                               err_msg=cell)
                    np.testing.assert_allclose(error, cpu_error, rtol=1e-8,
                                               atol=1e-10 * scale, err_msg=cell)


@pytest.mark.parametrize("name", list(ESTIMATORS))
def test_path_recycling_takes_what_records_and_refuses_the_rest(name):
    settings = dict(estimator=(name,), recycling="fixed")
    if ESTIMATORS[name].replayable:
        assert RetrievalConfig(**settings).recycling == "fixed"
    else:
        with pytest.raises(ValueError, match=f"{name!r} does not record: use 'score'"):
            RetrievalConfig(**settings)
