"""Path recycling (seed paper Sec. 5): stored forward paths, path sorting, correction
factors, and re-use policies. See docs/recycling.md."""

from cloudct.recycling.policy import AdaptiveESS, FixedPeriod
from cloudct.recycling.recycler import Evaluation, Recycler
from cloudct.recycling.replay import (
    correction_log_weights,
    effective_sample_size,
    replay_batch_gradients,
    replay_gradient,
    replay_images,
    replay_render,
)
from cloudct.recycling.store import PathStore, record_paths, sort_paths
from cloudct.recycling.store_memory import MemoryBudgetError

__all__ = [
    "AdaptiveESS",
    "Evaluation",
    "FixedPeriod",
    "MemoryBudgetError",
    "PathStore",
    "Recycler",
    "correction_log_weights",
    "effective_sample_size",
    "record_paths",
    "replay_batch_gradients",
    "replay_gradient",
    "replay_images",
    "replay_render",
    "sort_paths",
]
