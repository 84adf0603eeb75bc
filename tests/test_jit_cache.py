"""The on-disk cache of compiled kernels (cloudct.jit_cache): a change to a routine that a
kernel calls, in any module, recompiles the kernel; a change elsewhere does not; the cache
lives where $CLOUDCT_CACHE_DIR says and `cloudct cache --clear` empties it."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numba
import pytest

from cloudct.jit_cache import (
    PACKAGE_ROOT,
    compile_clock,
    imported_files,
    source_closure,
    source_stamp,
)


def _clear_memos() -> None:
    for memoised in (imported_files, source_closure, source_stamp):
        memoised.cache_clear()


@pytest.fixture
def package(tmp_path):
    """A package ``pkg``: a imports b (module level) and c (inside a function, relatively);
    b imports nothing of the package; d is imported by nobody."""
    root = tmp_path / "pkg"
    root.mkdir()
    (root / "__init__.py").write_text("")
    (root / "a.py").write_text("import numpy\nfrom pkg.b import f\n\n"
                               "def g():\n    from . import c\n    return c\n")
    (root / "b.py").write_text("def f():\n    return 1\n")
    (root / "c.py").write_text("import os\n")
    (root / "d.py").write_text("from pkg import a\n")
    yield root
    _clear_memos()


def test_the_closure_follows_every_import_of_the_package(package):
    names = {p.name for p in source_closure(package / "a.py", package)}
    assert names == {"a.py", "b.py", "c.py", "__init__.py"}  # `from . import c`: the package
    assert {p.name for p in source_closure(package / "b.py", package)} == {"b.py"}
    assert {p.name for p in source_closure(package / "d.py", package)} == names | {"d.py"}


def test_the_stamp_changes_with_a_callee_and_not_with_an_unrelated_module(package):
    before = source_stamp(package / "a.py", package)
    (package / "d.py").write_text("from pkg import a\nx = 2\n")  # imports a, a does not import it
    _clear_memos()
    assert source_stamp(package / "a.py", package) == before
    (package / "b.py").write_text("def f():\n    return 2\n")
    _clear_memos()
    assert source_stamp(package / "a.py", package) != before


def test_the_kernels_closure_holds_the_engine_and_not_the_layers_above():
    closure = {str(p.relative_to(PACKAGE_ROOT)) for p in
               source_closure(PACKAGE_ROOT / "mc" / "cuda_kernels.py")}
    assert {"mc/forward.py", "mc/traversal.py", "mc/accumulate.py", "mc/sample_matching.py",
            "physics/phase.py", "physics/mixing.py", "mc/random.py"} <= closure
    assert not any(name.startswith(("retrieval/", "cli/", "distributed/")) for name in closure)
    replay = {str(p.relative_to(PACKAGE_ROOT)) for p in
              source_closure(PACKAGE_ROOT / "recycling" / "cuda_replay.py")}
    assert {"recycling/replay_kernels.py", "recycling/path_terms.py"} <= replay


# A cross-module call: russian_roulette (mc/events.py) draws with uniform (mc/random.py).
_COMPILE = textwrap.dedent("""
    import json
    from cloudct.mc.events import russian_roulette
    from cloudct.mc.random import stream_start
    russian_roulette(5, 2, 0.5, stream_start(1, 2, 3))
    stats = russian_roulette.stats
    print(json.dumps([sum(stats.cache_hits.values()), sum(stats.cache_misses.values())]))
""")


def _run(code: str, copy: Path, cache: Path, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(copy), CLOUDCT_CACHE_DIR=str(cache))
    env.pop("NUMBA_CACHE_DIR", None)
    return subprocess.run([sys.executable, "-c", code, *args], env=env, capture_output=True,
                          text=True, check=True, cwd=copy)


def test_a_cached_kernel_is_reused_until_a_routine_it_calls_changes(tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(PACKAGE_ROOT, copy / "cloudct", ignore=shutil.ignore_patterns("__pycache__"))
    cache = tmp_path / "cache"

    def hits_and_misses() -> list[int]:
        return json.loads(_run(_COMPILE, copy, cache).stdout.splitlines()[-1])

    assert hits_and_misses() == [0, 1]  # compiled
    assert hits_and_misses() == [1, 0]  # loaded
    kernels = cache / "kernels"
    assert any(p.name.startswith("events.russian_roulette") for p in kernels.rglob("*.nbi"))
    with (copy / "cloudct" / "cli" / "render.py").open("a") as f:  # not called by it
        f.write("\n# an edit of the command line\n")
    assert hits_and_misses() == [1, 0]
    with (copy / "cloudct" / "mc" / "random.py").open("a") as f:  # a routine it calls
        f.write("\n# an edit of the random streams\n")
    assert hits_and_misses() == [0, 1]  # stale: compiled again
    assert hits_and_misses() == [1, 0]
    shown = _run("from cloudct.cli import main; main(['cache'])", copy, cache).stdout
    assert str(kernels) in shown and "MiB" in shown
    cleared = _run("from cloudct.cli import main; main(['cache', '--clear'])", copy, cache)
    assert "cleared" in cleared.stdout and not kernels.exists()


def test_the_cuda_kernels_use_the_same_cache(tmp_path):
    """numba-cuda's cache takes cloudct's locator (compiling needs a GPU: not here)."""
    code = textwrap.dedent("""
        import cloudct.mc.cuda_kernels as k, cloudct.recycling.cuda_replay as r
        for kernel in (k.forward_render_kernel, k.sample_matching_gradient_kernel,
                       r.replay_gradient_kernel):
            locator = kernel._cache._impl.locator
            print(type(locator).__name__, locator.get_cache_path())
    """)
    env = dict(os.environ, CLOUDCT_CACHE_DIR=str(tmp_path))
    env.pop("NUMBA_ENABLE_CUDASIM", None)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         check=True).stdout.splitlines()
    assert len(out) == 3
    for line in out:
        name, path = line.split(" ", 1)
        assert name == "CloudctCacheLocator" and path.startswith(str(tmp_path / "kernels"))


def test_the_compile_clock_times_compiling_and_not_calling():
    @numba.njit
    def square(x):
        return x * x

    with compile_clock() as first:
        square(3.0)
    with compile_clock() as again:
        square(4.0)
    assert first.seconds > 0.0 and again.seconds == 0.0
