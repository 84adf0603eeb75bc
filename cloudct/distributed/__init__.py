"""Scale-out over Dask (``pip install 'cloudct[distributed]'``): photon batches traced on
Dask workers, images and gradients reduced on the client in batch order, bitwise as in one
process; path recycling with the stored paths kept on the workers. Importing this package
does not import Dask; a client is only needed when one is used.

- :mod:`.cluster`: clients and local clusters (:func:`connect`, :func:`local_cluster`);
- :mod:`.executor`: :class:`DaskExecutor`, what the engine's ``executor=`` takes;
- :mod:`.batches`: the worker tasks and the ordered reduction;
- :mod:`.recycling`: path stores kept on the workers.

See docs/distributed.md."""

from cloudct.distributed.cluster import (
    DistributedError,
    close_client,
    connect,
    local_cluster,
    worker_environment,
)
from cloudct.distributed.executor import DaskExecutor, executor
from cloudct.distributed.recycling import DistributedPathStore, DistributedRecycler

__all__ = [
    "DaskExecutor",
    "DistributedError",
    "DistributedPathStore",
    "DistributedRecycler",
    "close_client",
    "connect",
    "executor",
    "local_cluster",
    "worker_environment",
]
