"""Sphinx configuration of the tlsjax documentation (built by ``./scripts/docs``).

Why Sphinx (issue 40): the API reference comes from the docstrings as they are written (reST
with ``:func:`` cross-references, no Google/NumPy sections, so no napoleon), the CLI reference
from ``tlsjax._cli.build_parser()`` (sphinx-argparse), the guides' examples run in this one
Python process (``sphinx.ext.doctest``: each JAX program compiles once for every page, where a
kernel per page would compile it again), the notebooks render with their committed outputs
(myst-nb, execution off: the test suite already runs them), and ``-W`` turns a broken reference,
a stale example or an undocumented public name into a failed build. MkDocs with mkdocstrings
would have needed the docstrings rewritten and an executor per page.
"""

import os
import pathlib
import sys

os.environ.setdefault("JAX_PLATFORMS", "cpu")

DOCS = pathlib.Path(__file__).resolve().parent
ROOT = DOCS.parent
sys.path.insert(0, str(DOCS / "_ext"))
sys.path.insert(0, str(ROOT))

import tlsjax  # noqa: E402

project = "tlsjax"
author = "the tlsjax authors"
copyright = "the tlsjax authors, Apache-2.0"
release = version = tlsjax.__version__

extensions = [
    "myst_nb",  # Markdown pages (myst-parser) and the notebooks
    "sphinx.ext.autodoc",
    "sphinx.ext.doctest",
    "sphinx.ext.mathjax",
    "sphinx-mathjax-offline",  # MathJax copied into the site: the equations render offline
    "sphinxarg.ext",
    "tlsjax_docs",  # API pages from tlsjax/__init__.py, benchmark figures, SPEC links
]

exclude_patterns = ["_build", "Thumbs.db", ".DS_Store", "_ext"]
html_theme = "furo"
html_title = f"tlsjax {release}"
html_static_path = []
html_show_sourcelink = False

# Markdown: $...$ maths, ::: fences, heading anchors for cross-page links.
myst_enable_extensions = ["dollarmath", "colon_fence", "deflist"]
myst_heading_anchors = 3
# The notebooks are executed by tests/test_notebooks.py and committed with their outputs.
nb_execution_mode = "off"
nb_merge_streams = True

# Every reference to a public tlsjax object must resolve; references to other packages' types in
# signatures (numpy, jax, jaxtyping, builtins) cannot without intersphinx, which would need the
# network at build time.
nitpicky = True
# Private names (tlsjax._...) that docstrings mention are not documented either.
nitpick_ignore_regex = [(r"py:.*", r"(?!tlsjax\b).*"), (r"py:.*", r"tlsjax\._.*")]

autodoc_default_options = {"members": True, "member-order": "bysource"}
autodoc_typehints = "signature"
autodoc_inherit_docstrings = False
add_module_names = True
python_display_short_literal_types = True

# Every page's examples start in a fresh empty folder (files they write stay out of the
# repository) with numpy, tlsjax and the runner of ``tlsjax-cli`` command lines.
doctest_global_setup = f"""
import os, tempfile
os.environ.setdefault("JAX_PLATFORMS", "cpu")
_DOCS_CWD, _DOCS_TMP = os.getcwd(), tempfile.mkdtemp(prefix="tlsjax-docs-")
os.chdir(_DOCS_TMP)
REPO = {str(ROOT)!r}
import numpy as np
import tlsjax as tj
from tlsjax_docs import run_cli as _tlsjax_cli
"""
# ... and leave nothing behind (the pages write scans, JSONs and reports).
doctest_global_cleanup = """
import shutil
os.chdir(_DOCS_CWD)
shutil.rmtree(_DOCS_TMP, ignore_errors=True)
"""
doctest_default_flags = (
    __import__("doctest").ELLIPSIS
    | __import__("doctest").NORMALIZE_WHITESPACE
    | __import__("doctest").DONT_ACCEPT_TRUE_FOR_1
)
