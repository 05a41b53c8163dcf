"""Notebooks stay true: every committed ``notebooks/NN_*.ipynb`` runs top to bottom, as committed.

The test reads the committed notebook, clears its outputs and executes its code cells in order
with the ``python3`` kernel from the repository root: the cells are not edited. The kernel
inherits ``TLSJAX_NOTEBOOK_FAST=1``; a notebook whose full run takes minutes reads that variable
in its first code cell (shown to the reader) and runs fewer Monte Carlo runs or optimiser steps,
and runs in full without it, as a reader's fresh kernel does. XLA compiles without its backend
optimisations (compiling dominates these runs) and the kernels share the suite's compilation
cache. A cell that raises fails the test, so an API change that breaks a notebook fails CI.

Two cheap checks keep the committed files honest: each notebook was saved executed (every code
cell run, in order, none raising), and its cells are those its builder ``notebooks/_make_NN.py``
writes (regenerate with ``python notebooks/_make_NN.py``, which executes and saves it).
"""

import importlib.util
import pathlib
import sys

import nbclient
import nbformat
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("[0-9][0-9]_*.ipynb"))
IDS = [p.stem for p in NOTEBOOKS]


def _built(path):
    """The notebook as its builder makes it (not executed)."""
    maker = path.parent / f"_make_{path.name[:2]}.py"
    spec = importlib.util.spec_from_file_location(f"_make_{path.name[:2]}", maker)
    module = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(maker.parent))  # the builders import notebooks/_nbtools.py
    try:
        spec.loader.exec_module(module)  # builders only collect cells unless run as __main__
    finally:
        sys.path.remove(str(maker.parent))
    return module.BUILD.notebook()


def test_every_notebook_is_found():
    names = [p.name for p in NOTEBOOKS]
    assert len(names) >= 5 and all(
        (ROOT / "notebooks" / f"_make_{n[:2]}.py").exists() for n in names
    )


@pytest.mark.parametrize("path", NOTEBOOKS, ids=IDS)
def test_committed_notebook_is_its_builders_and_was_executed(path):
    nb = nbformat.read(path, as_version=4)
    built = _built(path)
    assert [(c.cell_type, c.source) for c in nb.cells] == [
        (c.cell_type, c.source) for c in built.cells
    ], f"{path.name} differs from its builder: run python notebooks/_make_{path.name[:2]}.py"
    code = [c for c in nb.cells if c.cell_type == "code"]
    counts = [c.execution_count for c in code]
    assert counts == list(range(1, len(code) + 1)), f"{path.name} was not saved executed in order"
    errors = [o for c in code for o in c.outputs if o.output_type == "error"]
    assert not errors, f"{path.name} was saved with an error output"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=IDS)
def test_notebook_runs_top_to_bottom(path, monkeypatch):
    # The kernel inherits these: the notebooks' fast mode, and the suite's quick-compile XLA
    # flags and compilation cache (tests/conftest.py), shared with the other kernels.
    monkeypatch.setenv("TLSJAX_NOTEBOOK_FAST", "1")
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")
    nb = nbformat.read(path, as_version=4)
    for cell in nb.cells:
        if cell.cell_type == "code":
            cell.outputs, cell.execution_count = [], None
    client = nbclient.NotebookClient(
        nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(ROOT)}}
    )
    client.execute()  # raises CellExecutionError naming the cell and the traceback
    errors = [
        o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"
    ]
    assert not errors
