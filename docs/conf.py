"""Sphinx configuration of distilkit's documentation site: ``python -m sphinx -b html -W --keep-going docs SITE``.

The pages are the Markdown files under docs/ (MyST-Parser reads them as GitHub renders them); the API pages under
``reference/api/`` pull docstrings in with autodoc (``{eval-rst}`` + ``automodule``). No intersphinx: the build runs
without network (.ci/run builds the site with ``-W``, so every warning fails CI).
"""

from __future__ import annotations

import sys
from pathlib import Path

_ROOT = Path(__file__).resolve().parent.parent
if str(_ROOT) not in sys.path:  # the checkout's package, installed or not
    sys.path.insert(0, str(_ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # _cli.py: the parser reference/cli.md documents

import distilkit  # noqa: E402  (after the path: the project's name and version come from the package)

project = distilkit.__name__
version = release = distilkit.__version__

needs_sphinx = "8.1"  # the docs extra's lower bound (pyproject.toml)
extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.viewcode",
    "sphinxarg.ext",  # sphinx-argparse: reference/cli.md, every command read from distilkit.cli.build_parser
]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
root_doc = "index"
# _build: a local build's output; examples/: the worked plug-in's files, linked from the guide, not pages
exclude_patterns = ["_build", "examples/**"]

# every cross-reference must resolve (a docstring's :class:/:func: that names nothing on the site is an error under
# -W); the libraries distilkit's signatures name (torch, pydantic, numpy, the standard library) have no pages here:
# no intersphinx, the build runs without network
nitpicky = True
nitpick_ignore_regex = [
    (r"py:.*", r"(torch|pydantic|numpy|np|pathlib|typing|collections|abc|enum|argparse|rich|safetensors)(\..*)?"),
    (r"py:class", r"(Tensor|BaseModel|Module|Parameter|Path|Generator|Optimizer|device|dtype|ndarray)"),
    (r"py:class", r"distilkit\.registry\.T"),  # the registry's type variable: the component's type
    (r"py:class", r"'.*"),  # a dataclass's signature keeps its fields' annotations as the quoted strings they are
]

# no typographic quotes or dashes: `--jobs 2` and 'stages.*.train.steps=4' in the command-line reference (and any
# prose) must paste into a shell as they are shown
smartquotes = False

# MyST: the GitHub-style `#section` links the pages use resolve for headings down to ###
myst_heading_anchors = 3
myst_enable_extensions = ["colon_fence"]  # ::: fences for directives; no dollarmath: no page writes maths in $…$

# autodoc: members in the source's order, type hints in the descriptions (the signatures stay short)
autodoc_member_order = "bysource"
autodoc_typehints = "description"

html_theme = "furo"
html_title = f"distilkit {release}"
