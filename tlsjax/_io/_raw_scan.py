"""What a point-cloud format reader hands on to :mod:`._point_clouds` (the readers of E57, LAS/LAZ,
PCD and PLY and the text formats all return :class:`RawScan`), and the pose convention of the
files' transforms."""

from __future__ import annotations

import dataclasses

import numpy as np

from .._model._geometry import angles_from_matrix


@dataclasses.dataclass
class RawScan:
    """What a format reader hands on: coordinates in the file's frame, as stored (n, 3), the
    pose stored in the file (or None), whether the coordinates are object space, and notes."""

    name: str
    points: np.ndarray
    pose: np.ndarray | None = None
    object_frame: bool = False
    notes: list = dataclasses.field(default_factory=list)
    index: np.ndarray | None = None  # row of each point in the file's scan (None: 0..n-1)
    n_stored: int | None = None


def pose_from_transform(R_obj_from_scanner, translation) -> np.ndarray:
    """EOP (S, omega, phi, kappa) of ``X = A x + t``: ``R = A^T``, ``S = t``."""
    return np.concatenate(
        [
            np.asarray(translation, dtype=np.float64),
            angles_from_matrix(np.asarray(R_obj_from_scanner).T),
        ]
    )
