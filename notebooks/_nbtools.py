"""Shared notebook builder for the ``_make_NN.py`` scripts: collect cells, execute top to bottom
with the ``python3`` Jupyter kernel from the repository root, write the notebook with outputs."""

import pathlib
import sys
import time

import nbclient
import nbformat
from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook

HERE = pathlib.Path(__file__).resolve().parent


class Builder:
    def __init__(self, name: str):
        self.out = HERE / name
        self.cells = []

    def md(self, text):
        self.cells.append(new_markdown_cell(text.strip("\n")))

    def code(self, text):
        self.cells.append(new_code_cell(text.strip("\n")))

    def notebook(self):
        nb = new_notebook(cells=self.cells)
        nb.metadata["kernelspec"] = {
            "name": "python3",
            "display_name": "Python 3",
            "language": "python",
        }
        nb.metadata["language_info"] = {"name": "python"}
        return nb

    def run(self, timeout=900):
        nb = self.notebook()
        t0 = time.perf_counter()
        nbclient.NotebookClient(
            nb,
            timeout=timeout,
            kernel_name="python3",
            resources={"metadata": {"path": str(HERE.parent)}},
        ).execute()
        nbformat.write(nb, self.out)
        print(f"executed and wrote {self.out} in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
