"""Scale-out over Dask (``pip install 'cloudct[distributed]'``): photon batches traced on
Dask workers, images and gradients reduced on the client in batch order, bitwise as in one
process; path recycling with the stored paths kept on the workers. Importing this package
does not import Dask; a client is only needed when one is used. See :mod:`.core` and
docs/distributed.md."""

from cloudct.distributed.core import (
    DaskExecutor,
    DistributedError,
    close_client,
    connect,
    executor,
    local_cluster,
    worker_environment,
)
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
