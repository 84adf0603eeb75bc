"""The package's shape: one-way layers (the import-linter contracts in pyproject.toml), no
import cycles, and modules a reader can hold.

The contracts are checked on every import statement, including those inside functions, so
a new import that runs back up a layer fails here; a small package with such an import
shows that it does.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

import grimp
import pytest
from importlinter import cli

REPO = Path(__file__).resolve().parents[1]
MAX_MODULE_LINES = 550


def lint_imports(**options) -> int:
    """import-linter's ``lint_imports``, without its side effect on the process: its logging
    set-up (``logging.config.dictConfig``) disables every logger that exists, cloudct's
    too, which would silence the ``cloudct`` log of the tests that run after it in this
    process."""
    loggers = [logger for logger in logging.Logger.manager.loggerDict.values()
               if isinstance(logger, logging.Logger)]
    disabled = [logger.disabled for logger in loggers]
    try:
        return cli.lint_imports(**options)
    finally:
        for logger, state in zip(loggers, disabled, strict=True):
            logger.disabled = state


@pytest.fixture
def in_repo(monkeypatch):
    """Run from the repository root with its packages first on the path."""
    monkeypatch.chdir(REPO)
    monkeypatch.syspath_prepend(str(REPO))


def test_the_layer_contracts_are_kept(in_repo):
    assert lint_imports(config_filename="pyproject.toml", no_cache=True, no_logo=True) == 0


def test_a_function_level_import_up_a_layer_breaks_the_contract(tmp_path, monkeypatch):
    package = tmp_path / "layered"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "high.py").write_text("from layered import low\n")
    (package / "low.py").write_text("def f():\n    from layered import high\n    return high\n")
    config = tmp_path / "contracts.toml"
    config.write_text(
        '[tool.importlinter]\nroot_package = "layered"\n\n'
        '[[tool.importlinter.contracts]]\nname = "down only"\ntype = "layers"\n'
        'layers = ["layered.high", "layered.low"]\n'
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path)
    assert lint_imports(config_filename=str(config), no_cache=True, no_logo=True) == 1


def test_no_module_imports_itself_through_others(in_repo):
    graph = grimp.build_graph("cloudct", exclude_type_checking_imports=True)
    cycles = []
    for module in sorted(graph.modules):
        for imported in graph.find_modules_directly_imported_by(module):
            chain = graph.find_shortest_chain(importer=imported, imported=module)
            if chain is not None:
                cycles.append(" -> ".join((module, *chain)))
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_no_module_is_longer_than_a_reader_can_hold():
    lengths = {
        str(path.relative_to(REPO)): sum(1 for _ in path.open())
        for path in (REPO / "cloudct").rglob("*.py")
    }
    too_long = {path: n for path, n in lengths.items() if n > MAX_MODULE_LINES}
    assert not too_long, f"modules over {MAX_MODULE_LINES} lines: {too_long}"


def test_the_engine_runs_without_the_scale_out_layer(in_repo):
    """Rendering imports nothing of cloudct.distributed (nor Dask)."""
    code = (
        "import sys\n"
        "import cloudct.mc.gradient, cloudct.mc.render, cloudct.recycling\n"
        "bad = [m for m in sys.modules if m.startswith(('cloudct.distributed', 'dask', "
        "'distributed'))]\n"
        "assert not bad, bad\n"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO, env=env)
