"""Regenerate the pictures of the documentation and the README from the demo.

``python docs/make_figures.py`` runs ``tlsjax demo`` (the simulated Chow et al. 2013 room, seed
0) into a temporary folder and copies its residual plot to ``docs/img/demo_residuals.png``.
"""

import os
import pathlib
import shutil
import sys
import tempfile

os.environ.setdefault("JAX_PLATFORMS", "cpu")

from tlsjax._cli import main  # noqa: E402

IMG = pathlib.Path(__file__).resolve().parent / "img"


def make() -> int:
    with tempfile.TemporaryDirectory() as tmp:
        rc = main(["demo", "--out", tmp])
        if rc:
            return rc
        IMG.mkdir(exist_ok=True)
        shutil.copyfile(pathlib.Path(tmp) / "residuals.png", IMG / "demo_residuals.png")
    print(f"wrote {IMG / 'demo_residuals.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(make())
