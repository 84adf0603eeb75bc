"""Compiling the kernels a run needs before it needs them, several at once.

numba compiles a kernel at its first call and keeps it in cloudct's kernel cache
(:mod:`cloudct.jit_cache`); a later process loads it in a fraction of a second. A cold run
would otherwise spend its first minutes compiling, one kernel after the other, while the
machine's other cores wait. Here each piece of work that compiles a distinct set of kernels
is a *warm-up task*: it traces a handful of paths through those kernels on a small problem
(the bundled single cloud seen by three 8 x 8 cameras), whose arrays have the types of
every run's, so that what it leaves in the cache is what a run loads:

- ``render:M``: the images by method M (:data:`cloudct.mc.render.METHODS`);
- ``gradient:E``: the gradient by estimator E (:data:`cloudct.mc.gradient.ESTIMATORS`);
- ``recycling``: path recycling's recording and replays (a two-iteration retrieval).

:func:`warm_up` runs tasks in parallel processes (``cloudct cache --warm``);
:class:`BackgroundWarmUp` runs the tasks of a retrieval's settings (:func:`tasks_for`) in
other processes while the retrieval loads its measurements and carves, and the retrieval
waits for them before its first iteration (``cloudct retrieve``, ``cloudct demo``). The
tasks only fill the cache: a run's results do not depend on whether they ran.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.pool
import os
import time
import warnings
from collections.abc import Iterable
from pathlib import Path

import numpy as np
import xarray as xr

from cloudct.jit_cache import compile_clock, kernel_cache_dir, source_stamp
from cloudct.les import bundled_single_cloud
from cloudct.mc.gradient import ESTIMATORS, gradient_estimate
from cloudct.mc.render import METHODS, render
from cloudct.mc.scene import Scene, build_scene
from cloudct.measurements import synthesize_measurements
from cloudct.medium import cell_edges
from cloudct.optics import DEFAULT_OPTICS, to_optical
from cloudct.retrieval.config import RetrievalConfig

#: Every warm-up task's name (see the module docstring).
TASKS = (*(f"render:{m}" for m in METHODS), *(f"gradient:{e}" for e in ESTIMATORS), "recycling")
#: Paths each task traces: enough to reach every kernel's code, too few to take time.
PATHS = 64
#: The environment variable that turns compiling ahead in retrieve and demo off ("0").
AHEAD_SWITCH = "CLOUDCT_COMPILE_AHEAD"


def small_problem(optics: str = DEFAULT_OPTICS) -> tuple[xr.Dataset, Scene]:
    """The warm-up tasks' medium (the bundled single cloud with ``optics``) and scene (the
    single-cloud preset's zenith camera and two of its ring, 8 x 8 pixels each)."""
    medium = to_optical(bundled_single_cloud(), optics=optics)
    lo, hi = (np.array([e[i] for e in cell_edges(medium)]) for i in (0, -1))
    return medium, build_scene(lo, hi, preset="single-cloud", npix=8, azimuths=[0.0, 180.0])


def _marker(name: str, backend: str, optics: str) -> Path:
    """The file whose presence says that task ``name`` ran on ``backend`` with ``optics``
    since the last change to any module its kernels come from."""
    stamp = source_stamp(Path(__file__).resolve())[:16]
    return kernel_cache_dir() / "warm" / f"{name.replace(':', '-')}.{backend}.{optics}.{stamp}"


def pending(tasks: Iterable[str], backend: str, optics: str = DEFAULT_OPTICS) -> list[str]:
    """The ``tasks`` that have not run since the last change to cloudct's kernels (those
    done leave their kernels in the cache)."""
    return [t for t in dict.fromkeys(tasks) if not _marker(t, backend, optics).exists()]


def _check_task(name: str) -> None:
    if name not in TASKS:
        raise ValueError(f"warm-up task must be one of {TASKS}, got {name!r}")


def run_task(name: str, backend: str = "cpu", optics: str = DEFAULT_OPTICS) -> float:
    """Run the warm-up task ``name`` (one of :data:`TASKS`) in this process on ``backend``;
    returns the seconds it spent compiling or loading kernels (the rest is tracing)."""
    _check_task(name)
    medium, scene = small_problem(optics)
    kind, _, which = name.partition(":")
    with compile_clock() as clock:
        if kind == "render":
            combined = {"pixel_samples": 2} if which == "combined" else {}
            render(medium, scene, photons=PATHS, method=which, batches=2, progress=False,
                   backend=backend, **combined)
        elif kind == "gradient":
            residual = np.ones((len(scene.cameras), 8, 8))
            gradient_estimate(medium, scene, residual, estimator=which, photons=PATHS,
                              batches=2, backend=backend)
        else:
            from cloudct.retrieval.loop import Retrieval  # the loop imports this module

            measurements = synthesize_measurements(medium, scene, photons=PATHS, batches=2,
                                                   progress=False, backend=backend)
            config = RetrievalConfig(iterations=2, photons=PATHS, recycling="fixed", period=2,
                                     checkpoint_every=10**6)
            Retrieval(measurements, medium, config, backend=backend).run(progress=False)
    marker = _marker(name, backend, optics)
    marker.parent.mkdir(parents=True, exist_ok=True)
    marker.touch()
    return clock.seconds


def tasks_for(config: RetrievalConfig, carving: bool) -> list[str]:
    """The warm-up tasks whose kernels a retrieval with ``config`` runs, but the forward
    render's when it carves its start (the carving's fit compiles it, in the run's
    process)."""
    tasks = [f"render:{config.image_method}", *(f"gradient:{e}" for e in config.estimator)]
    if config.recycling != "none" or config.optimizer == "lbfgsb":
        tasks.append("recycling")
    return [t for t in dict.fromkeys(tasks) if not (carving and t == "render:forward")]


def _pool(jobs: int) -> multiprocessing.pool.Pool:
    # spawned, not forked: a forked child would inherit this process's numba and CUDA state
    return multiprocessing.get_context("spawn").Pool(jobs)


def _jobs(tasks: list[str], jobs: int | None) -> int:
    return jobs or max(1, min(len(tasks), len(os.sched_getaffinity(0))))


def warm_up(tasks: Iterable[str] = TASKS, *, backend: str = "cpu",
            optics: str = DEFAULT_OPTICS, jobs: int | None = None) -> dict[str, float]:
    """Run the warm-up ``tasks`` in ``jobs`` parallel processes (default: one per task, at
    most the CPUs this process may use); returns each task's compile (or load) seconds."""
    tasks = list(dict.fromkeys(tasks))
    for name in tasks:
        _check_task(name)
    pool = _pool(_jobs(tasks, jobs))
    try:
        results = {name: pool.apply_async(run_task, (name, backend, optics)) for name in tasks}
        seconds = {name: r.get() for name, r in results.items()}
        pool.close()  # the processes end on their own (killed, they would leak locks)
        return seconds
    finally:
        pool.terminate()
        pool.join()


class BackgroundWarmUp:
    """The :func:`pending` ones of the warm-up ``tasks`` running in other processes while
    this one goes on (none where the environment sets :data:`AHEAD_SWITCH` to "0");
    :meth:`wait` before their kernels are needed, or :meth:`stop` them."""

    def __init__(self, tasks: Iterable[str], *, backend: str, optics: str = DEFAULT_OPTICS):
        off = os.environ.get(AHEAD_SWITCH, "1") == "0"
        self.tasks = [] if off else pending(tasks, backend, optics)
        self.started = time.perf_counter()
        self._pool = _pool(_jobs(self.tasks, None)) if self.tasks else None
        self._results = {name: self._pool.apply_async(run_task, (name, backend, optics))
                         for name in self.tasks}

    def wait(self) -> float:
        """Wait for every task; returns the wall seconds since the start (0 when none
        ran). A task that failed is reported by a warning, not raised: the run compiles
        what it lacks itself, and fails there if it must."""
        if self._pool is None:
            return 0.0
        for name, result in self._results.items():
            result.wait()
            if not result.successful():
                try:
                    result.get()
                except Exception as error:  # reported, the run goes on
                    warnings.warn(f"compiling ahead ({name}) failed: {error!r}; the run "
                                  "compiles its kernels itself", RuntimeWarning, stacklevel=2)
        self._pool.close()  # the processes end on their own (killed, they would leak locks)
        self._pool.join()
        self._pool = None
        return time.perf_counter() - self.started

    def stop(self) -> None:
        """End the processes now (those still compiling leave nothing in the cache)."""
        if self._pool is not None:
            self._pool.terminate()
            self._pool.join()
            self._pool = None
