"""Notebook 05 runs top to bottom in its fast mode (TLSJAX_NOTEBOOK_FAST=1: 2 starts x 20 steps,
a coarser point cloud); the committed notebook holds the full run's outputs."""

import os
import pathlib
import sys

import pytest

nbclient = pytest.importorskip("nbclient")

ROOT = pathlib.Path(__file__).resolve().parent.parent


def test_notebook_05_fast(tmp_path, monkeypatch):
    sys.path.insert(0, str(ROOT / "notebooks"))
    try:
        import _make_05
    finally:
        sys.path.pop(0)
    monkeypatch.setenv("TLSJAX_NOTEBOOK_FAST", "1")
    monkeypatch.setenv("JAX_PLATFORMS", os.environ.get("JAX_PLATFORMS", "cpu"))
    nb = _make_05.BUILD.notebook()
    nbclient.NotebookClient(
        nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(ROOT)}}
    ).execute()
    text = "\n".join(
        o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
    )
    assert "fast mode: True" in text
    assert "optimised vs paper" in text and "greedy: boards" in text
