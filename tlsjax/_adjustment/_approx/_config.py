"""Settings and results of the approximate values."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..._units import DEG


@dataclasses.dataclass(frozen=True)
class ApproxConfig:
    """Tolerances of the approximate values.

    A (scan, primitive) correspondence is consistent when its normals agree within
    ``max(angle_tol, 4 sigma)`` and its centroid or target lies within
    ``max(distance_tol, 4 sigma)`` of the other scans' primitive, sigma propagated from the local
    fits. ``normal_sigma_floor`` [rad] and ``point_sigma_floor`` [m] are the model error of a local
    normal and point (uncorrected APs, unflat walls). A local normal needs at least
    ``min_spread`` [m] RMS extent of its points along their second principal axis.
    ``rounds``: rounds of re-registration of every scan against all the others after the
    scans are placed along the spanning tree. ``minimal_planes``: the best-determined shared
    planes whose pairs make rotation hypotheses. ``hypotheses``: minimal target triples tried
    per registration (RANSAC).
    """

    angle_tol: float = 3.0 * DEG
    distance_tol: float = 0.10
    normal_sigma_floor: float = 0.2 * DEG
    point_sigma_floor: float = 0.005
    min_spread: float = 0.02
    rounds: int = 1
    minimal_planes: int = 6
    hypotheses: int = 12

    def __post_init__(self):
        for name in ("angle_tol", "distance_tol", "normal_sigma_floor", "point_sigma_floor"):
            if not getattr(self, name) > 0:
                raise ValueError(f"ApproxConfig.{name} must be positive, got {getattr(self, name)}")
        if int(self.rounds) < 0 or int(self.hypotheses) < 1:
            raise ValueError(
                f"ApproxConfig.rounds must be >= 0 and hypotheses >= 1, got {self.rounds} and "
                f"{self.hypotheses}"
            )


@dataclasses.dataclass(frozen=True)
class Inconsistency:
    """A (scan, primitive) correspondence that disagrees with the other scans: the angle [rad]
    between its normal and theirs (NaN for targets and planes without a local normal) and the
    RMS distance [m] of its points from their plane, or of its target from theirs."""

    scan: str
    kind: str
    name: str
    angle: float
    distance: float

    def __str__(self) -> str:
        ang = "" if np.isnan(self.angle) else f"normal {self.angle / DEG:.2f} deg off, "
        return (
            f"scan {self.scan}, {self.kind} {self.name}: {ang}{self.distance * 1e3:.0f} mm "
            "from the other scans"
        )


@dataclasses.dataclass(frozen=True, eq=False)
class Approximation:
    """Approximate values of a network and what the registration learnt about its data.

    ``targets`` (t, 3), ``eops`` (s, 6) = (Xs, Ys, Zs, omega, phi, kappa), ``planes`` (k, 4) =
    (n, d) with ``n . X = d``, in the frame of :mod:`._frame`.

    Gross errors (for a robust start, SPEC section 7): ``target_inlier`` (n,) in the network's
    target row order and ``plane_inlier`` (m,) in its plane row order are False for the
    observations whose (scan, primitive) correspondence disagrees with the other scans at the
    registered poses (a target metres off, a swapped name, a target or plane match in the wrong
    scan); ``inconsistent`` lists those correspondences with their misfit. A primitive seen in
    one scan only cannot be checked and counts as an inlier. ``tree`` is the order in which
    the scans were placed, as (scan, the placed scan it shares most with, or None for the
    first), ``registrations`` per placed scan (scan, inlier correspondences, shared ones) of
    its registration against the scans placed before it.
    """

    targets: np.ndarray
    eops: np.ndarray
    planes: np.ndarray
    inconsistent: tuple = ()
    tree: tuple = ()
    target_inlier: np.ndarray | None = None
    plane_inlier: np.ndarray | None = None
    registrations: tuple = ()
