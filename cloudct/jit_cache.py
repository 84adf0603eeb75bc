"""The on-disk cache of compiled kernels: where it lives and when an entry is stale.

numba caches a compiled function (``cache=True``) keyed on the modification time and size of
the file that defines it, and of that file alone. A kernel compiles every routine it calls
into its machine code, so after a change to a routine in another module (the engine's
kernels call across ``mc``, ``physics`` and ``recycling``) numba would load the old kernel.
cloudct therefore gives numba, and numba-cuda, its own cache locator for the functions it
defines:

- **Where**: ``$CLOUDCT_CACHE_DIR/kernels`` (default ``$XDG_CACHE_HOME/cloudct/kernels``, else
  ``~/.cache/cloudct/kernels``), one folder per installed copy of cloudct. CPU functions
  and CUDA kernels are cached there alike (a CUDA kernel is keyed on the GPU's compute
  capability too, by numba-cuda).
- **When stale**: a function's freshness stamp is the SHA-256 of the source of its module
  and of every cloudct module that module imports, directly or through others (the
  ``import`` statements read from the files, those inside functions included). A change to
  any routine a kernel can call therefore recompiles it; a change elsewhere (the command
  line, the retrieval loop) does not.
- **Clearing**: ``cloudct cache`` prints the folder and its size, ``cloudct cache --clear``
  empties it (:func:`clear_kernel_cache`).

The locator is installed when :mod:`cloudct` is imported (:func:`install_cpu_locator`), and
for CUDA kernels when the CUDA back end is imported (:func:`install_cuda_locator`), before
any cloudct function is compiled. Functions defined outside cloudct keep numba's locators.

**How long**: :func:`compile_clock` times what a stretch of code spent compiling functions
or loading them from this cache (a retrieval's log keeps it apart from its iterations'
tracing, :mod:`cloudct.retrieval.photon_budget`).
"""

from __future__ import annotations

import ast
import hashlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from functools import cache
from pathlib import Path

from numba.core import event

#: The folder of the cloudct package whose functions this cache holds.
PACKAGE_ROOT = Path(__file__).resolve().parent


def cache_root() -> Path:
    """cloudct's cache folder: ``$CLOUDCT_CACHE_DIR``, else ``$XDG_CACHE_HOME/cloudct`` or
    ``~/.cache/cloudct`` (Mie tables and compiled kernels live there)."""
    root = os.environ.get("CLOUDCT_CACHE_DIR")
    if root:
        return Path(root)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "cloudct"


def kernel_cache_dir() -> Path:
    """The folder of this copy of cloudct's compiled kernels (under :func:`cache_root`)."""
    copy = hashlib.sha1(str(PACKAGE_ROOT).encode()).hexdigest()[:12]
    return cache_root() / "kernels" / copy


def clear_kernel_cache() -> int:
    """Delete every cached kernel of every copy of cloudct; returns the bytes freed."""
    folder = cache_root() / "kernels"
    freed = folder_size(folder)
    shutil.rmtree(folder, ignore_errors=True)
    return freed


def folder_size(folder: Path) -> int:
    """Bytes of the files under ``folder`` (0 if it does not exist)."""
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def _module_file(name: str, root: Path) -> Path | None:
    """The source file of module ``name`` of the package at ``root`` (None if none)."""
    parts = name.split(".")
    if parts[0] != root.name:
        return None
    base = root.joinpath(*parts[1:])
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _module_name(path: Path, root: Path) -> str:
    parts = path.relative_to(root.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@cache
def imported_files(path: Path, root: Path = PACKAGE_ROOT) -> frozenset[Path]:
    """Source files of the modules of the package at ``root`` that the module at ``path``
    imports directly (every ``import`` statement, at any depth of the module)."""
    package = _module_name(path, root)
    if path.name != "__init__.py":
        package = package.rpartition(".")[0]
    names: list[str] = []
    for node in ast.walk(ast.parse(path.read_bytes())):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the package, `level - 1` packages up
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*up, base] if base else up)
            names.append(base)
            names += [f"{base}.{alias.name}" for alias in node.names]  # submodules
    files = (_module_file(name, root) for name in names)
    return frozenset(f for f in files if f is not None and f != path)


@cache
def source_closure(path: Path, root: Path = PACKAGE_ROOT) -> tuple[Path, ...]:
    """The module at ``path`` and every module of the package it imports, directly or
    through others, sorted."""
    seen = {path}
    todo = [path]
    while todo:
        for f in imported_files(todo.pop(), root):
            if f not in seen:
                seen.add(f)
                todo.append(f)
    return tuple(sorted(seen))


@cache
def source_stamp(path: Path, root: Path = PACKAGE_ROOT) -> str:
    """SHA-256 of the sources of :func:`source_closure` (names and contents): the
    freshness stamp of every compiled function defined at ``path``."""
    h = hashlib.sha256()
    for f in source_closure(path, root):
        h.update(str(f.relative_to(root)).encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()


class _CloudctLocator:
    """Cache locator of the functions defined in cloudct (see the module docstring); numba
    asks each locator class in turn, and this one answers for cloudct's files only."""

    def __init__(self, py_func, py_file: str):
        self._py_file = Path(py_file).resolve()
        self._lineno = py_func.__code__.co_firstlineno
        folder = self._py_file.parent.relative_to(PACKAGE_ROOT.parent)
        self._cache_path = str(kernel_cache_dir() / folder)

    def ensure_cache_path(self) -> None:
        """Create the folder and check that it is writable."""
        os.makedirs(self._cache_path, exist_ok=True)
        tempfile.TemporaryFile(dir=self._cache_path).close()

    def get_cache_path(self) -> str:
        """The folder of this function's index and compiled overloads."""
        return self._cache_path

    def get_source_stamp(self) -> str:
        """The freshness stamp: :func:`source_stamp` of the defining module."""
        return source_stamp(self._py_file)

    def get_disambiguator(self) -> str:
        """Tells apart functions of the same name in one module (their first line)."""
        return str(self._lineno)

    @classmethod
    def from_function(cls, py_func, py_file: str):
        """A locator for a function defined in cloudct, else None (numba's own locators
        follow; also where the cache folder cannot be written)."""
        path = Path(py_file).resolve()
        if not path.is_file() or PACKAGE_ROOT not in path.parents:
            return None
        locator = cls(py_func, py_file)
        try:
            locator.ensure_cache_path()
        except OSError:
            return None
        return locator


def _install(cache_impl, locator_base) -> None:
    """Put a cloudct locator first in ``cache_impl``'s locator classes (once)."""
    classes = cache_impl._locator_classes
    if classes and issubclass(classes[0], _CloudctLocator):
        return
    locator = type("CloudctCacheLocator", (_CloudctLocator, locator_base), {"__module__": __name__})
    cache_impl._locator_classes = [locator, *classes]


def install_cpu_locator() -> None:
    """Cache cloudct's ``@njit`` functions with :class:`_CloudctLocator` (idempotent)."""
    from numba.core import caching

    _install(caching.CacheImpl, caching._CacheLocator)


def install_cuda_locator() -> None:
    """Cache cloudct's CUDA kernels with :class:`_CloudctLocator` (needs numba-cuda;
    idempotent)."""
    from numba.cuda.core import caching

    _install(caching.CacheImpl, caching._CacheLocator)


class CompileClock(event.TimingListener):
    """The wall time numba held its compiler lock while the clock listened: compiling a
    function, or loading it from the cache (numba's and numba-cuda's dispatchers both take
    the lock for either; a compilation inside another counts once)."""

    @property
    def seconds(self) -> float:
        """Seconds spent compiling or loading (0 when nothing was)."""
        return self.duration if self.done else 0.0


@contextmanager
def compile_clock() -> Iterator[CompileClock]:
    """A :class:`CompileClock` listening while the context runs (to be read after it)."""
    clock = CompileClock()
    with event.install_listener("numba:compiler_lock", clock):
        yield clock
