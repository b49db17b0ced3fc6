"""Sphinx configuration of the selfcal documentation (``make docs``).

Sphinx + numpydoc (docstrings), sphinx-click (the CLI reference, generated from the
click commands) and MyST (the Markdown format pages). Only the public API is
autodocumented; ``nitpicky`` is off so that a cross-reference to a private helper in
a docstring is not an error, while every other warning is (``-W --keep-going``).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
os.environ.setdefault("MPLBACKEND", "Agg")

project = "selfcal"
author = "selfcal contributors"
copyright = "selfcal contributors"  # noqa: A001
release = version = "0.1.0"

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "numpydoc",
    "sphinx_click",
    "myst_parser",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "README.md"]
root_doc = "index"
nitpicky = False
suppress_warnings = [
    "myst.header",  # the format pages start at ## under their # title
    "misc.highlighting_failure",  # abbreviated JSON examples ("...") in the format pages
    "myst.xref_missing",  # links to repository files (examples/, benchmarks/) outside the site
]

# autodoc: documented members only, in source order, with type hints in the signature
autodoc_default_options = {"members": True, "member-order": "bysource", "undoc-members": False}
autodoc_typehints = "signature"
autodoc_preserve_defaults = True
autosummary_generate = False

# numpydoc: no per-attribute autosummary tables (they need stub pages); no validation
# of other modules' docstrings beyond what Sphinx itself parses
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False
numpydoc_validation_checks: set[str] = set()

myst_enable_extensions = ["dollarmath"]
myst_heading_anchors = 3

html_theme = "alabaster"
html_title = "selfcal"
html_static_path = ["_static"]
html_css_files = ["selfcal.css"]  # code blocks scroll within their column (no overflow)
# no "smart" quotes / dashes: the CLI reference must show --speed, not an en dash (copy-paste)
smartquotes = False
html_theme_options = {"description": "Self-calibration of sensor networks", "fixed_sidebar": True}


def _write_degeneracy_table() -> None:
    """docs/_generated/degeneracies.rst from the registry (one source of truth)."""
    from selfcal.errors import Degeneracy

    rows = [".. list-table::", "   :header-rows: 1", "   :widths: 25 75", "",
            "   * - kind", "     - meaning"]
    for d in Degeneracy:
        rows += [f"   * - ``{d.value}``", f"     - {d.explanation}"]
    out = Path(__file__).parent / "_generated" / "degeneracies.rst"
    out.parent.mkdir(exist_ok=True)
    text = "\n".join(rows) + "\n"
    if not out.is_file() or out.read_text() != text:
        out.write_text(text)


_write_degeneracy_table()
