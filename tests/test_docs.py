"""The documentation site builds with warnings as errors, and its tutorials run as written.

The site (``sphinx-build -W -b html docs docs/_build/html``, the README's docs command) holds
the API reference generated from the docstrings; a docstring that reStructuredText cannot
parse, a broken cross-reference or a page outside every table of contents fails the build.
Each tutorial's Python blocks are executed in order, in one namespace, in an empty folder,
as a reader would paste them (they use small photon counts).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parents[1] / "docs"
TUTORIALS = sorted((DOCS / "tutorials").glob("*.md"))


def python_blocks(page: Path) -> list[str]:
    """The ```python blocks of a Markdown page, in order."""
    return re.findall(r"^```python\n(.*?)^```", page.read_text(), flags=re.S | re.M)


@pytest.mark.filterwarnings("ignore::DeprecationWarning")  # Sphinx's own extensions on
@pytest.mark.filterwarnings("ignore::PendingDeprecationWarning")  # Sphinx's next API
def test_the_site_builds_without_warnings(tmp_path):
    from sphinx.cmd.build import build_main

    status = build_main(["-W", "--keep-going", "-q", "-b", "html", "-d",
                         str(tmp_path / "doctrees"), str(DOCS), str(tmp_path / "html")])
    assert status == 0, "sphinx-build -W failed: see the warnings above"
    assert (tmp_path / "html" / "api" / "rendering.html").exists()


@pytest.mark.parametrize("page", [p for p in TUTORIALS if python_blocks(p)], ids=lambda p: p.stem)
def test_the_tutorial_runs_as_written(page, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": f"tutorial_{page.stem}"}
    for k, block in enumerate(python_blocks(page)):
        exec(compile(block, f"{page.relative_to(DOCS.parent)} block {k + 1}", "exec"), namespace)


def test_every_tutorial_has_code():
    assert [p.stem for p in TUTORIALS if p.stem != "index" and not python_blocks(p)] == []


@pytest.mark.parametrize("page", ["benchmarks.md", "benchmarks_log.md"])
def test_every_benchmark_command_shown_reproduces_its_run(page):
    """Each ``python -m benchmarks ...`` command of the page starts (the benchmark exists and
    its options parse; it is stopped before it runs), and a retrieval's options give the
    settings recorded in its result file (benchmarks.__main__.settings_drift)."""
    import netCDF4  # noqa: F401 - sets HDF5_PLUGIN_PATH when first imported: its own doing

    from benchmarks.__main__ import page_commands, parse_error

    environment = dict(os.environ)
    commands = page_commands(DOCS / page)
    assert len(commands) >= 10
    assert [e for c in commands if (e := parse_error(c))] == []
    # importing a benchmark changes nothing of the process (a NUMBA_NUM_THREADS set on
    # import made every later parallel kernel of the test session refuse to run)
    assert dict(os.environ) == environment


def test_the_command_check_catches_what_does_not_reproduce():
    from benchmarks.__main__ import parse_error

    assert "invalid float value" in parse_error(["retrieval.single_cloud", "--minutes", "soon"])
    # a 2026-11-25 run recorded the 2 % threshold schedule, which is no longer the default
    old = ["retrieval.single_cloud", "--truth", "benchmarks/work/two_cumuli.nc", "--minutes",
           "60", "--stages", "2", "--photons", "200000", "--image-photons", "4", "--step", "1.0",
           "--sparsity", "0.01", "--estimator", "score", "--output",
           "benchmarks/results/retrieval_two_cumuli_60min_score.json"]
    assert "--schedule threshold" in parse_error(old)


def docstring_example_modules() -> list[str]:
    """The cloudct modules whose docstrings hold examples (``>>>``)."""
    package = Path(__file__).resolve().parents[1] / "cloudct"
    return sorted(".".join(f.relative_to(package.parent).with_suffix("").parts)
                  for f in package.rglob("*.py") if ">>> " in f.read_text())


@pytest.mark.parametrize("module", docstring_example_modules())
def test_the_docstring_examples_run(module):
    import doctest
    import importlib

    result = doctest.testmod(importlib.import_module(module), verbose=False,
                             optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0 and result.failed == 0
