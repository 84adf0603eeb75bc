"""Stopping a retrieval cleanly: SIGTERM or Ctrl-C ends it at the end of the current
iteration, with its checkpoint written, instead of wherever the signal lands.

While :func:`stop_requests` is active (in the main thread), the first SIGTERM or SIGINT
only records itself and says so on stderr; the loop checks it after each iteration, writes
the checkpoint and raises :class:`RunStopped`, from which the run resumes bitwise as if it
had never stopped. The handlers of before are put back at once, so that a second signal acts
as it would have (SIGTERM ends the process, Ctrl-C raises KeyboardInterrupt).
"""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

#: The signals that stop a run at the end of its iteration.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


@dataclass
class StopRequest:
    """The signal received while :func:`stop_requests` listened (None: none)."""

    signum: int | None = None


@contextmanager
def stop_requests() -> Iterator[StopRequest]:
    """Listen for :data:`STOP_SIGNALS` while the context runs (in the main thread only:
    elsewhere Python delivers no signals and the request stays empty)."""
    request = StopRequest()
    if threading.current_thread() is not threading.main_thread():
        yield request
        return
    before = {s: signal.getsignal(s) for s in STOP_SIGNALS}

    def record(signum: int, frame) -> None:
        request.signum = signum
        for s, handler in before.items():
            signal.signal(s, handler)
        print(f"cloudct: {signal.Signals(signum).name} received: stopping at the end of this "
              "iteration, with a checkpoint (send it again to stop now)", file=sys.stderr)

    for s in STOP_SIGNALS:
        signal.signal(s, record)
    try:
        yield request
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)


class RunStopped(Exception):
    """A run stopped by a signal at the end of iteration ``iteration``, its state in
    ``checkpoint`` (None: the run had none; the :class:`~cloudct.retrieval.loop.Retrieval`
    object still holds it)."""

    def __init__(self, signum: int, iteration: int, checkpoint: Path | None):
        self.signum = signum
        self.iteration = iteration
        self.checkpoint = checkpoint
        kept = f"checkpoint {checkpoint}" if checkpoint is not None else "no checkpoint file"
        super().__init__(f"stopped by {signal.Signals(signum).name} after iteration "
                         f"{iteration}; {kept}")
