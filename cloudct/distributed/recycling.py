"""Path recycling with the stored paths kept on the Dask workers (stateful placement).

A :class:`DistributedPathStore` is a path store split into parts, contiguous ranges of
batches; each part is a :class:`~cloudct.recycling.store.PathStore` of its batches, held in
the memory of one worker as the result of a Dask future (recorded there, never sent back).
Re-evaluations are tasks that depend on a part's future, so the scheduler runs them on the
worker that holds it: a recycled iteration moves the medium (scattered once to every
worker), the residual, and the per-batch images and gradients and a summary of the
correction factors (24 bytes per batch, :func:`~cloudct.recycling.replay.weight_summary`)
back, never the paths: the bytes do not depend on the number of paths. Should a worker
die, the scheduler re-records its parts elsewhere from the same seed (the futures'
lineage): the same paths, bitwise.

A part's store holds the same paths as the corresponding batches of
:func:`~cloudct.recycling.store.record_paths` with the same seed (photon index
``b * per_batch + k`` of batch b), and each batch is re-evaluated on its own, so images,
gradients, standard errors and ESS are bitwise those of one process, whatever the number of
workers or parts.

:class:`DistributedRecycler` is :class:`~cloudct.recycling.Recycler` on such stores.

:func:`record_part` is :func:`~cloudct.recycling.store.record_paths` on a range of batches;
:class:`DistributedRecycler` overrides only the store operations of
:class:`~cloudct.recycling.Recycler`.
"""

from __future__ import annotations

import math
import time
import uuid
from collections.abc import Callable

import numpy as np
import xarray as xr

from cloudct.distributed.batches import nbytes
from cloudct.distributed.cluster import DistributedError
from cloudct.distributed.executor import executor
from cloudct.mc.estimate import check_residual, kernel_inputs
from cloudct.mc.scene import Scene
from cloudct.medium import cell_edges
from cloudct.recycling.recycler import Evaluation, Recycler
from cloudct.recycling.replay import (
    correction_log_weights,
    replay_batch_gradients,
    replay_images,
    summary_ess,
    weight_summary,
)
from cloudct.recycling.store import STORAGE, PathStore, check_same_grid, record_paths

# ------------------------------------------------------------------------------------------
# Worker side: recording a range of batches, re-evaluating it
# ------------------------------------------------------------------------------------------


def record_part(
    medium: xr.Dataset, scene: Scene, *, seed: int, per_batch: int, start: int, count: int,
    **kwargs,
) -> PathStore:
    """The paths of batches ``start .. start + count - 1`` of
    :func:`~cloudct.recycling.store.record_paths` (same seed, same ``per_batch``) as a
    store of ``count`` batches (the other arguments as ``record_paths``)."""
    return record_paths(
        medium, scene, photons=per_batch * (start + count), seed=seed, batches=start + count,
        first_batch=start, nbatch=count, **kwargs,
    )


def part_summary(store: PathStore) -> dict:
    """Sizes of a part (runs where the part lives; only this small dict travels)."""
    return {**store.summary(), "records": store.records, "events": store.events}


def part_log_weights(store: PathStore, medium: xr.Dataset) -> np.ndarray:
    """:func:`~cloudct.recycling.replay.weight_summary` of the part's paths (per batch)."""
    from cloudct.distributed.batches import _fault

    _fault("log_weights", store.info.get("first_batch", 0))
    return weight_summary(correction_log_weights(store, medium), store.batches)


def part_replay(store: PathStore, medium: xr.Dataset, residual, mis_ratio: float = 0.0) -> tuple:
    """Per-batch images (``residual`` None) or gradients of the part, batch means as
    :func:`~cloudct.recycling.replay.replay_images` (``mis_ratio`` > 0: the combined
    estimator's forward half), with the per-batch summary of the paths' log r and the
    events."""
    from cloudct.distributed.batches import _fault

    _fault("replay", store.info.get("first_batch", 0))
    if residual is None:
        values, info = replay_images(store, medium, mis_ratio=mis_ratio)
    else:
        values, info = replay_batch_gradients(store, medium, residual, mis_ratio=mis_ratio)
    return values, info["weight_summary"], info["events"], info["wall_time"]


# ------------------------------------------------------------------------------------------
# Client side
# ------------------------------------------------------------------------------------------


class DistributedPathStore:
    """A path store whose parts live on the Dask workers (see the module documentation).

    Has the attributes of :class:`~cloudct.recycling.store.PathStore` that describe it
    (``paths``, ``batches``, ``per_batch``, ``seed``, ``rr_depth``, ``rr_survival``,
    ``storage``, ``sorted``, ``edges``, ``scene``, ``nbytes``, ``records``, ``events``) and
    the operations of :mod:`cloudct.recycling.replay` as methods, with the same results.
    """

    def __init__(self, ex, medium: xr.Dataset, scene: Scene, *, batches: int,
                 options: dict):
        """Not recorded yet (:meth:`record` makes one): ``options`` are
        :func:`record_part`'s keywords but ``start`` and ``count``."""
        self.executor = ex
        self.scene = scene
        self.edges = tuple(np.asarray(e, float) for e in cell_edges(medium))
        self.batches = int(batches)
        self.options = options
        self.seed, self.per_batch = options["seed"], options["per_batch"]
        self.rr_depth, self.rr_survival = options["rr_depth"], options["rr_survival"]
        # (first batch, batches, future of the part's PathStore, None before recording)
        self.parts = [(start, count, None) for start, count in ex.ranges(self.batches)]
        # the medium and scene the parts were recorded from and their futures, held as long
        # as the parts: the scheduler records a part lost with its worker again from the
        # futures; should they be lost too (scattered data has no lineage, and Dask keeps
        # one copy of data no task waits for), the parts are recorded again from these
        self.recorded_from = ((medium, None), (scene, None))
        self.summaries: list[dict] = []

    @classmethod
    def record(
        cls, client, medium: xr.Dataset, scene: Scene, *, photons: int, seed: int = 0,
        batches: int = 32, storage: str = "auto", memory_budget: float | None = None,
        sort: bool = True, rr_depth: int = 100, rr_survival: float = 0.95,
        variable: np.ndarray | None = None,
    ) -> DistributedPathStore:
        """Record ``photons`` paths on the workers (arguments as
        :func:`~cloudct.recycling.store.record_paths`; ``memory_budget`` is the total over
        all parts, shared in proportion to their batches)."""
        if int(photons) < 1:
            raise ValueError(f"photons must be a positive count, got {photons}")
        if int(batches) < 2:
            raise ValueError(f"batches must be at least 2 for standard errors, got {batches}")
        if storage not in STORAGE:
            raise ValueError(f"storage must be one of {STORAGE}, got {storage!r}")
        t0 = time.perf_counter()
        ex = executor(client)
        kernel_inputs(medium, scene)  # validate here, not on the workers
        store = cls(ex, medium, scene, batches=int(batches), options=dict(
            seed=int(seed), per_batch=math.ceil(int(photons) / batches), storage=storage,
            memory_budget=memory_budget, sort=sort, rr_depth=int(rr_depth),
            rr_survival=float(rr_survival), variable=variable,
        ))
        sent = store._record_parts()
        tag = uuid.uuid4().hex[:8]
        store.summaries = ex.gather([
            ex.submit(part_summary, f, key=f"cloudct-paths-summary-{tag}-{s}")
            for s, _, f in store.parts
        ])
        store._describe(sent, time.perf_counter() - t0)
        return store

    def _record_parts(self) -> int:
        """Submit the recording of every part not held by a worker (all of them at first;
        later, those lost with their workers together with their medium or scene): each
        its batches, the paths of :func:`~cloudct.recycling.store.record_paths` with the
        same seed. Returns the bytes sent."""
        ex = self.executor
        (medium, _), (scene, _) = self.recorded_from
        medium_future, sent = ex.share(medium, cache=True)
        scene_future, more = ex.share(scene, cache=True)
        self.recorded_from = ((medium, medium_future), (scene, scene_future))
        tag = uuid.uuid4().hex[:8]
        budget = self.options["memory_budget"]
        # the parts go to the workers in turn, so that each holds its share of the paths'
        # memory (the scheduler alone may queue them all on one worker); a loose
        # restriction: a part whose worker is gone is recorded elsewhere
        workers = ex.addresses()
        parts = []
        for i, (start, count, future) in enumerate(self.parts):
            if future is None or future.status != "finished":
                future = ex.submit(
                    record_part, medium_future, scene_future, start=start, count=count,
                    **{**self.options, "memory_budget": None if budget is None
                       else budget * count / self.batches},
                    key=f"cloudct-paths-{tag}-{start}", workers=[workers[i % len(workers)]],
                    allow_other_workers=True,
                )
            parts.append((start, count, future))
        self.parts = parts
        return sent + more

    def _describe(self, sent: int, record_time: float) -> None:
        """The store's sizes and kind from its parts' summaries."""
        self.info = {"record_time": record_time, "bytes_to_workers": sent}
        storages = sorted({s["storage"] for s in self.summaries})
        self.storage = storages[0] if len(storages) == 1 else "mixed"
        self.sorted = all(s["sorted"] for s in self.summaries)

    # -- sizes ------------------------------------------------------------------------------

    @property
    def paths(self) -> int:
        return self.per_batch * self.batches

    @property
    def nbytes(self) -> int:
        """Memory held by the parts on the workers, together."""
        return int(sum(s["bytes"] for s in self.summaries))

    @property
    def records(self) -> int:
        return int(sum(s["records"] for s in self.summaries))

    @property
    def events(self) -> int:
        return int(sum(s["events"] for s in self.summaries))

    def placement(self) -> dict[int, tuple[str, ...]]:
        """Workers holding each part, by first batch."""
        who = self.executor.client.who_has([f for _, _, f in self.parts])
        return {s: tuple(who[f.key]) for s, _, f in self.parts}

    def release(self) -> None:
        """Free the parts on the workers."""
        self.executor.client.cancel([f for _, _, f in self.parts])
        self.parts = []
        self.recorded_from = ()

    # -- operations -------------------------------------------------------------------------

    def _run(self, func, share: Callable[[], tuple[tuple, int]], *,
             desc: str) -> tuple[list, int, int]:
        """The results of ``func(part, *shared)`` on each part (where it is held), where
        ``share()`` scatters the shared arguments (``(shared, bytes sent)``); the bytes
        they moved back, and the bytes sent (the shared arguments, and the recording of
        lost parts)."""
        ex = self.executor

        def inputs() -> tuple[tuple, int]:
            # parts lost with a worker, together with the medium or scene they were
            # recorded from, are recorded again from those kept here (the same paths); the
            # shared arguments lost with it are scattered again
            sent = self._record_parts() if self._lost() else 0
            shared, more = share()
            return (tuple(f for _, _, f in self.parts), *shared), sent + more

        def submit(parts: tuple, *shared) -> list:
            tag = uuid.uuid4().hex[:8]
            # run each part's task where the part is held (a loose restriction: if its
            # holder is gone, the part is recomputed and the task runs elsewhere)
            try:
                holders = ex.client.who_has(list(parts))
            except Exception:  # a part lost meanwhile: placement is a hint only
                holders = {}
            return [ex.submit(func, f, *shared, key=f"cloudct-{desc}-{tag}-{s}",
                              **({"workers": list(holders[f.key]), "allow_other_workers": True}
                                 if holders.get(f.key) else {}))
                    for (s, _, _), f in zip(self.parts, parts, strict=True)]

        results, sent = ex.gather_shared(inputs, submit)
        if len(results) != len(self.parts):
            raise DistributedError("results of a recycled evaluation are missing")
        covered = [(s, n) for s, n, _ in self.parts]
        expected = 0
        for s, n in covered:
            if s != expected:
                raise DistributedError(f"path store parts do not cover batch {expected}")
            expected += n
        if expected != self.batches:
            raise DistributedError(f"path store parts cover {expected} of {self.batches} batches")
        return results, sum(nbytes(r) for r in results), sent

    def _lost(self) -> bool:
        """Whether a part is no longer held by a worker."""
        return any(f.status != "finished" for _, _, f in self.parts)

    def log_weights(self, medium: xr.Dataset) -> tuple[np.ndarray, dict]:
        """The per-batch :func:`~cloudct.recycling.replay.weight_summary` of all paths'
        correction factors (batch order) and the bytes moved."""
        check_same_grid(self, cell_edges(medium))

        def share() -> tuple[tuple, int]:
            medium_future, sent = self.executor.share(medium, cache=True)
            return (medium_future,), sent

        results, received, sent = self._run(part_log_weights, share, desc="log-weights")
        summary = np.concatenate(results)
        if summary.shape[0] != self.batches:
            raise DistributedError(f"{summary.shape[0]} of {self.batches} batches came back")
        return summary, {"bytes_to_workers": sent, "bytes_from_workers": received}

    def replay(self, medium: xr.Dataset, residual: np.ndarray | None = None,
               mis_ratio: float = 0.0):
        """Per-batch images (float64[batches, view, row, col], ``residual`` None) or
        per-batch gradients (float64[batches, x, y, z]), batch means as in
        :mod:`cloudct.recycling.replay` (and its ``mis_ratio``), and info (events, ess,
        ess_fraction, weight_summary, wall_time, bytes moved)."""
        t0 = time.perf_counter()
        check_same_grid(self, cell_edges(medium))
        ex = self.executor
        if residual is not None:
            residual = check_residual(residual, self.scene)

        def share() -> tuple[tuple, int]:
            medium_future, sent = ex.share(medium, cache=True)
            residual_future, more = (None, 0) if residual is None else ex.share(residual)
            return (medium_future, residual_future, float(mis_ratio)), sent + more

        results, received, sent = self._run(
            part_replay, share,
            desc="recycled-images" if residual is None else "recycled-gradient",
        )
        for (_, n, _), r in zip(self.parts, results, strict=True):
            if r[0].shape[0] != n:
                raise DistributedError("a part returned the wrong number of batches")
        values = np.concatenate([r[0] for r in results])
        summary = np.concatenate([r[1] for r in results])
        ess = summary_ess(summary)[0]
        info = {
            "photons": self.paths,
            "events": int(sum(r[2] for r in results)),
            "wall_time": time.perf_counter() - t0,
            "worker_time": float(sum(r[3] for r in results)),
            "ess": ess,
            "ess_fraction": ess / self.paths,
            "storage": self.storage,
            "sorted": self.sorted,
            "seed": self.seed,
            "weight_summary": summary,
            "mis_ratio": float(mis_ratio),
            "bytes_to_workers": sent,
            "bytes_from_workers": received,
        }
        return values, info

    def replay_images(self, medium: xr.Dataset, mis_ratio: float = 0.0):
        """As :func:`cloudct.recycling.replay.replay_images`."""
        return self.replay(medium, None, mis_ratio)

    def replay_gradient(self, medium: xr.Dataset, residual: np.ndarray, mis_ratio: float = 0.0):
        """As :func:`cloudct.recycling.replay.replay_gradient`: ``(mean, std_error, info)``."""
        values, info = self.replay(medium, residual, mis_ratio)
        return (
            values.mean(axis=0),
            values.std(axis=0, ddof=1) / math.sqrt(self.batches),
            info,
        )


class DistributedRecycler(Recycler):
    """:class:`~cloudct.recycling.Recycler` with its path stores on the Dask workers of
    ``client`` (a client, address or :class:`~cloudct.distributed.DaskExecutor`); the same
    arguments otherwise (``memory_budget``: bytes over all workers), the same evaluations,
    bitwise. ``info`` of each evaluation adds ``bytes_to_workers`` and
    ``bytes_from_workers``."""

    def __init__(self, scene: Scene, *, client=None, **kwargs) -> None:
        super().__init__(scene, **kwargs)
        self.executor = executor(client)
        self._moved = [0, 0]  # bytes to and from the workers in the current evaluation

    # the store operations of Recycler.evaluate, on the distributed stores

    def _release_store(self, store) -> None:
        if store is not None:
            store.release()

    def _record_store(
        self, medium: xr.Dataset, *, photons: int, seed: int, memory_budget: float | None
    ) -> DistributedPathStore:
        store = DistributedPathStore.record(
            self.executor, medium, self.scene, photons=photons, seed=seed,
            batches=self.batches, storage=self.storage, memory_budget=memory_budget,
            sort=self.sort, rr_depth=self.rr_depth, rr_survival=self.rr_survival,
            variable=self.variable,
        )
        self._moved[0] += store.info["bytes_to_workers"]
        return store

    def _log_weights(self, store, medium: xr.Dataset) -> np.ndarray:
        log_r, moved = store.log_weights(medium)
        self._count(moved)
        return log_r

    def _replay_images(
        self, store, medium: xr.Dataset, mis_ratio: float = 0.0
    ) -> tuple[np.ndarray, dict]:
        values, info = store.replay_images(medium, mis_ratio)
        self._count(info)
        return values, info

    def _replay_gradient(
        self, store, medium: xr.Dataset, residual: np.ndarray, mis_ratio: float = 0.0
    ) -> tuple:
        mean, std_error, info = store.replay_gradient(medium, residual, mis_ratio)
        self._count(info)
        return mean, std_error, info

    def _extra_info(self) -> dict:
        return {"bytes_to_workers": self._moved[0], "bytes_from_workers": self._moved[1]}

    def evaluate(
        self,
        medium: xr.Dataset,
        residual: Callable[[xr.Dataset], np.ndarray] | np.ndarray | None = None,
    ) -> Evaluation:
        """As :meth:`cloudct.recycling.Recycler.evaluate`, counting the bytes moved."""
        self._moved = [0, 0]
        return super().evaluate(medium, residual)

    def _count(self, info: dict) -> None:
        self._moved[0] += info.get("bytes_to_workers", 0)
        self._moved[1] += info.get("bytes_from_workers", 0)


__all__ = [
    "DistributedPathStore",
    "DistributedRecycler",
    "part_replay",
    "record_part",
]
