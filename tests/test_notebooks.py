"""Notebooks stay true: every notebook runs top to bottom against today's code.

Each ``notebooks/NN_*.ipynb`` is built from its builder ``notebooks/_make_NN.py`` (the source the
committed notebook is generated from) and executed (its code cells, in order, with the
``python3`` kernel from the repository root), in a fast mode: Monte Carlo run counts are lowered
(``runs=1000`` -> ``runs=FAST_RUNS``), notebook 03 simulates a coarser grid with fewer points
per plane, XLA compiles without its backend optimisations (compiling dominates these runs; it
halves them) and the kernels share one JAX compilation cache. A cell that raises fails the test,
so an API change that breaks a notebook fails CI. The outputs are not compared (they hold
timings); regenerate a notebook with ``python notebooks/_make_NN.py``.
"""

import importlib.util
import pathlib
import re
import sys

import nbclient
import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("[0-9][0-9]_*.ipynb"))
FAST_RUNS = 40
_FAST = [
    (re.compile(r"\bruns=1000\b"), f"runs={FAST_RUNS}"),
    (re.compile(r"^STEP = np\.deg2rad\(1\.5\)", re.M), "STEP = np.deg2rad(2.5)"),
    (re.compile(r"^MAX_POINTS = 200\b", re.M), "MAX_POINTS = 60"),
]


def fast_mode(nb):
    """The notebook with its Monte Carlo run counts lowered; returns how many cells changed."""
    changed = 0
    for cell in nb.cells:
        if cell.cell_type != "code":
            continue
        cell.outputs = []
        src = cell.source
        for pattern, repl in _FAST:
            src = pattern.sub(repl, src)
        changed += src != cell.source
        cell.source = src
    return changed


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
    assert len(names) >= 4 and all(
        (ROOT / "notebooks" / f"_make_{n[:2]}.py").exists() for n in names
    )


@pytest.fixture(scope="module")
def jax_cache(tmp_path_factory):
    return str(tmp_path_factory.mktemp("jax_cache"))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs_top_to_bottom(path, jax_cache, monkeypatch):
    # The kernel inherits these: faster compiles, shared across the notebooks.
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=0")
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", jax_cache)
    monkeypatch.setenv("JAX_PLATFORMS", "cpu")
    nb = _built(path)
    fast_mode(nb)
    client = nbclient.NotebookClient(
        nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(ROOT)}}
    )
    client.execute()  # raises CellExecutionError naming the cell and the traceback
    errors = [
        o for c in nb.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"
    ]
    assert not errors
