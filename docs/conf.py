"""Sphinx configuration of cloudct's documentation site (``sphinx-build -W -b html docs
docs/_build/html``; ``pip install ".[docs]"``)."""

from __future__ import annotations

import cloudct

project = "cloudct"
author = "the cloudct developers"
copyright = "2026, the cloudct developers"
version = release = cloudct.__version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.mathjax",
    "sphinx.ext.napoleon",
    "sphinx.ext.viewcode",
    "sphinxcontrib.mermaid",
]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
root_doc = "index"
exclude_patterns = ["_build", "figures/*.py"]
myst_heading_anchors = 3
myst_enable_extensions = ["dollarmath"]
myst_fence_as_directive = ["mermaid"]  # architecture.md's data-flow diagram

# API reference: the docstrings as written; their NumPy-style ("Parameters" / "Returns"
# underlined) and Google-style ("Args:") sections are both parsed (napoleon)
autodoc_member_order = "bysource"
autodoc_typehints = "none"
napoleon_use_rtype = False


def escape_plain_text_formulas(app, what, name, obj, options, lines: list[str]) -> None:
    """cloudct's docstrings write formulas as plain text (|r_d|, |g|^2), which
    reStructuredText would read as substitutions: keep their bars literal."""
    lines[:] = [line.replace("|", "\\|") for line in lines]


def setup(app) -> None:
    app.connect("autodoc-process-docstring", escape_plain_text_formulas)

html_theme = "pydata_sphinx_theme"
html_title = f"cloudct {release}"
html_theme_options = {
    "navigation_with_keys": False,
    "show_toc_level": 2,
}
html_static_path: list[str] = []
