"""Output files written whole or not at all.

Every file cloudct writes (netCDF results, checkpoints, measurements, media, images; report
and figure files; the Mie table cache) is written to a partial file beside its destination
and renamed onto it only once complete (:func:`written_whole`). A write that fails (a full
disk, a file-size limit, a kill) therefore leaves the previous file as it was and removes
the partial one, and the error (:class:`WriteError`) says in one line what failed, what the
file needed where that is known, and what its disk has free. Each process writes its own
partial file, so two runs writing the same output do not write into one file, and a long run
holds its outputs (:func:`exclusive`) so that a second one is refused at its start.
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


class WriteError(OSError):
    """An output file that could not be written (the previous one, if any, kept)."""


@contextmanager
def written_whole(path: str | os.PathLike, needed_bytes: float | None = None) -> Iterator[Path]:
    """A partial file beside ``path`` (same suffix, so that writers that read the format
    from it still do) for the block to write; renamed onto ``path`` when the block ends,
    removed when it fails. An OSError or RuntimeError (the netCDF library's HDF errors) is
    raised again as :class:`WriteError`, with ``needed_bytes`` (the file's expected size)
    in the message where given."""
    path = Path(path)
    partial = path.with_name(f".{path.stem}.{os.getpid()}.partial{path.suffix}")
    try:
        yield partial
        os.replace(partial, path)
    except (OSError, RuntimeError) as err:
        raise WriteError(_write_failure(path, needed_bytes, err)) from err
    finally:
        partial.unlink(missing_ok=True)


def save_figure(fig, path: str | os.PathLike, dpi: int = 110) -> None:
    """Save the matplotlib figure ``fig`` to ``path`` whole or not at all."""
    with written_whole(path) as partial:
        fig.savefig(partial, dpi=dpi)


def _write_failure(path: Path, needed_bytes: float | None, err: Exception) -> str:
    """One line on a failed write: the file, the reason, its size and the disk's free space."""
    reason = str(err).splitlines()[0] if str(err) else type(err).__name__
    try:
        free = f"{shutil.disk_usage(path.parent).free / 2**20:.1f} MiB free there"
    except OSError:
        free = "its folder cannot be read"
    needs = "" if needed_bytes is None else f"it needs about {needed_bytes / 2**20:.1f} MiB, "
    kept = "the previous file is kept" if path.exists() else "nothing was written"
    return f"could not write {path} ({reason}): {needs}{free}{_file_size_limit()}; {kept}"


def _file_size_limit() -> str:
    """``", files of at most N MiB (ulimit -f)"`` where this process's file size is limited,
    else ``""``."""
    try:
        import resource  # POSIX only
    except ImportError:
        return ""
    soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    return "" if soft == resource.RLIM_INFINITY else \
        f", files of at most {soft / 2**20:.2f} MiB (ulimit -f)"


class OutputInUse(FileExistsError):
    """An output that another running process is writing."""


@contextmanager
def exclusive(path: str | os.PathLike) -> Iterator[None]:
    """Hold the output ``path`` for this process while the block runs: a second process
    asking for it meanwhile gets :class:`OutputInUse`, naming this one. The lock is the
    operating system's on the file ``.NAME.lock`` beside ``path``, released when the block
    ends or the process does, however it ends; the block's end removes the file."""
    import fcntl  # POSIX only, as the command line is

    path = Path(path)
    if not path.parent.is_dir():
        raise FileNotFoundError(f"the folder of {path} does not exist (create it first)")
    lock = path.with_name(f".{path.name}.lock")
    while True:
        f = open(lock, "a+")  # noqa: SIM115 - closed below, on every way out
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            holder = f.read().strip() or "another process"
            f.close()
            raise OutputInUse(f"{path} is being written by {holder}: wait for it to end, or "
                              "write elsewhere (-o)") from None
        try:
            held = os.stat(lock).st_ino == os.fstat(f.fileno()).st_ino
        except FileNotFoundError:
            held = False
        if held:
            break
        f.close()  # its holder removed the file we locked: lock the one there now
    try:
        f.seek(0)
        f.truncate()
        f.write(f"process {os.getpid()} (cloudct, started {time.strftime('%Y-%m-%d %H:%M:%S')})")
        f.flush()
        yield
    finally:
        lock.unlink(missing_ok=True)  # while held: whoever opened it before locks a ghost
        f.close()
