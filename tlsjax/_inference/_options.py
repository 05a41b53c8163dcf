"""The settings of :func:`tlsjax.self_calibrate`, one small object per concern (SPEC sections 5
and 7), and :class:`CalibrationOptions`, which holds one of each.

* :class:`ScreeningOptions`: the robust start and screening of gross errors before the
  least-squares tests (family-wise level);
* :class:`tlsjax.PlaneScreeningOptions` (:mod:`._robust`): the IGG-III screening of plane points;
* :class:`VCEOptions`: variance component estimation;
* :class:`SnoopingOptions`: Baarda's data snooping (the w-test's level, what one rejection
  removes);
* :class:`TestOptions`: the other tests and their levels (global and group tests, AP t-tests,
  score tests of missing terms) and the reliability measures (the level and power an MDB is
  for);
* :class:`tlsjax.SelectionOptions` (:mod:`._selection`): stepwise AP selection;
* :class:`tlsjax.SolverOptions`: the adjustment itself.

A concern set to None does not run (``CalibrationOptions(vce=None)``: no VCE). Every level is
named for the test it is the level of.
"""

from __future__ import annotations

import dataclasses

from .._adjustment._config import SolverOptions
from .._stats import ALPHA0, POWER, non_centrality
from .._summary import Settings
from ._robust import PlaneScreeningOptions
from ._selection import SelectionOptions

#: What one rejection of data snooping removes: one scalar observation, or the target's three.
REMOVAL_UNITS = ("observation", "target")


def _level(owner: str, name: str, value: float) -> None:
    if not 0 < value < 1:
        raise ValueError(f"{owner}.{name} must be in (0, 1), got {value}")


@dataclasses.dataclass(frozen=True)
class ScreeningOptions(Settings):
    """Gross errors out before the least-squares tests, for any weighting.

    ``robust_start``: before the first least-squares adjustment, iteratively reweighted
    adjustments with a redescending weight find gross errors (metres, swapped names, a target
    in the wrong scan) that a first least-squares adjustment would spread over correct
    observations. Screening then removes, largest first, the observations whose robust
    w-test exceeds the family-wise critical value at ``family_level`` (Bonferroni over the
    tested observations: a clean network loses an observation with probability
    ``family_level``); it stops when more than ``max_share`` of the observations would go
    (then the model, not a few blunders, is wrong, and the run says so).
    """

    robust_start: bool = True
    family_level: float = 0.001
    max_share: float = 0.05

    def __post_init__(self):
        _level("ScreeningOptions", "family_level", self.family_level)
        if not 0 < self.max_share <= 1:
            raise ValueError(f"ScreeningOptions.max_share must be in (0, 1], got {self.max_share}")


@dataclasses.dataclass(frozen=True)
class VCEOptions(Settings):
    """Variance component estimation, one factor per group (range, hz, el, levelling, heading,
    AP priors; target networks: plane weights are held fixed, SPEC section 5). Stops when every
    ``|s_g^2 - 1|`` is below ``tolerance`` or after ``max_iterations``; a group whose
    redundancy is below ``min_redundancy`` keeps its a priori sigma (its estimate would be
    mostly noise)."""

    tolerance: float = 1e-3
    max_iterations: int = 30
    min_redundancy: float = 3.0

    def __post_init__(self):
        if not self.tolerance > 0:
            raise ValueError(f"VCEOptions.tolerance must be positive, got {self.tolerance}")
        if self.max_iterations < 1:
            raise ValueError(f"VCEOptions.max_iterations must be >= 1, got {self.max_iterations}")
        if not self.min_redundancy > 0:
            raise ValueError(
                f"VCEOptions.min_redundancy must be positive, got {self.min_redundancy}"
            )


@dataclasses.dataclass(frozen=True)
class SnoopingOptions(Settings):
    """Baarda's data snooping: the largest ``|w|`` above the critical value is removed and the
    network re-adjusted, until none is.

    ``w_test_level``: the level of each w-test (0.001: critical value 3.29), or
    ``critical_value`` directly; ``bonferroni``: divide the level by the number of tested
    observations (family-wise: no clean observation removed with probability 1 - level).
    The per-test default rejects about 0.1 % of clean observations, about two per
    2,000-observation network (measured: 63 false removals in 30 networks of 2,160
    observations, benchmarks/stats_rates.py); ``bonferroni=True, w_test_level=0.05``
    (k = 4.23 there) removed none while finding all 150 injected 20-sigma blunders.
    ``removal``: "observation" (one scalar observation) or "target" (the target's three
    observations in that scan); ``max_removals`` bounds the removals of screening and snooping.
    """

    w_test_level: float = 0.001
    critical_value: float | None = None
    bonferroni: bool = False
    removal: str = "observation"
    max_removals: int = 100

    def __post_init__(self):
        _level("SnoopingOptions", "w_test_level", self.w_test_level)
        if self.removal not in REMOVAL_UNITS:
            raise ValueError(
                f"SnoopingOptions.removal must be one of {REMOVAL_UNITS}, got {self.removal!r}"
            )
        if self.critical_value is not None and not self.critical_value > 0:
            raise ValueError(
                f"SnoopingOptions.critical_value must be positive, got {self.critical_value}"
            )
        if self.max_removals < 0:
            raise ValueError(f"SnoopingOptions.max_removals must be >= 0, got {self.max_removals}")


@dataclasses.dataclass(frozen=True)
class TestOptions(Settings):
    """The tests of a calibration and their levels, and the reliability measures.

    ``global_test_level``: the global test and the group variance tests (chi-square, two-sided);
    ``ap_test_level``: the AP t-tests; ``score_tests``: after the last adjustment, the score
    test of every candidate term not in the model (``candidates``, default every registered
    term of the model's naming), family-wise level ``score_test_level`` (screening compares
    them with the largest w-test, SPEC section 7, so that a systematic misfit is named, not
    removed). ``mdb_level`` and ``mdb_power``: the level of the w-test and the power the
    minimal detectable bias and external reliability are for (delta0 = 4.13 at 0.1 % and
    80 %); ``min_redundancy``: observations with a smaller redundancy number are flagged
    uncontrolled (and screening does not judge them).
    """

    __test__ = False  # not a pytest class, though its name starts with "Test"

    global_test_level: float = 0.05
    ap_test_level: float = 0.05
    score_tests: bool = True
    score_test_level: float = 0.05
    candidates: tuple | None = None
    mdb_level: float = ALPHA0
    mdb_power: float = POWER
    min_redundancy: float = 0.1

    def __post_init__(self):
        for name in ("global_test_level", "ap_test_level", "score_test_level", "mdb_level"):
            _level("TestOptions", name, getattr(self, name))
        _level("TestOptions", "mdb_power", self.mdb_power)
        if not 0 <= self.min_redundancy < 1:
            raise ValueError(
                f"TestOptions.min_redundancy must be in [0, 1), got {self.min_redundancy}"
            )
        if isinstance(self.candidates, str):
            object.__setattr__(self, "candidates", tuple(self.candidates.split()))

    @property
    def delta0(self) -> float:
        """Baarda's non-centrality of the MDB: ``N^-1(1 - mdb_level/2) + N^-1(mdb_power)``."""
        return non_centrality(self.mdb_level, self.mdb_power)


#: The concerns of :class:`CalibrationOptions` and their types (None: the concern does not run).
_CONCERNS = {
    "solver": SolverOptions,
    "screening": ScreeningOptions,
    "plane_screening": PlaneScreeningOptions,
    "vce": VCEOptions,
    "snooping": SnoopingOptions,
    "tests": TestOptions,
    "selection": SelectionOptions,
}
#: Concerns that always run (they cannot be None).
_ALWAYS = ("solver", "tests")


@dataclasses.dataclass(frozen=True)
class CalibrationOptions(Settings):
    """The settings of :func:`tlsjax.self_calibrate`, one object per concern; a concern set to
    None does not run. The defaults are those of ``tlsjax calibrate``:

    ``solver`` (:class:`tlsjax.SolverOptions`); ``screening`` (:class:`ScreeningOptions`: the
    robust start and screening, on); ``plane_screening`` (:class:`tlsjax.PlaneScreeningOptions`:
    with plane points and no snooping, the plane points are screened by IGG-III reweighting
    instead, on); ``vce`` (:class:`VCEOptions`, on: target networks only, plane weights are
    held fixed); ``snooping`` (:class:`SnoopingOptions`, off); ``tests``
    (:class:`TestOptions`: levels of the global, group, AP and score tests, reliability);
    ``selection`` (:class:`tlsjax.SelectionOptions`: stepwise AP selection on the screened
    observations, starting from the model's APs; off).
    """

    solver: SolverOptions = dataclasses.field(default_factory=SolverOptions)
    screening: ScreeningOptions | None = dataclasses.field(default_factory=ScreeningOptions)
    plane_screening: PlaneScreeningOptions | None = dataclasses.field(
        default_factory=PlaneScreeningOptions
    )
    vce: VCEOptions | None = dataclasses.field(default_factory=VCEOptions)
    snooping: SnoopingOptions | None = None
    tests: TestOptions = dataclasses.field(default_factory=TestOptions)
    selection: SelectionOptions | None = None

    def __post_init__(self):
        for name, kind in _CONCERNS.items():
            value = getattr(self, name)
            if value is None and name not in _ALWAYS:
                continue
            if not isinstance(value, kind):
                none = "" if name in _ALWAYS else " or None (off)"
                raise TypeError(
                    f"CalibrationOptions.{name} must be a tlsjax {kind.__name__}{none}, "
                    f"got {type(value).__name__}"
                )

    @property
    def removal(self) -> str:
        """What one rejection removes (:attr:`SnoopingOptions.removal`; one observation when
        snooping is off)."""
        return "observation" if self.snooping is None else self.snooping.removal

    @property
    def max_removals(self) -> int:
        """Most removals of screening and snooping together (:attr:`SnoopingOptions.max_removals`)."""
        return (self.snooping or SnoopingOptions()).max_removals

    @property
    def w_test_level(self) -> float:
        """The level of each w-test: snooping's, else the default 0.001 (the reweighting band of
        the robust start and the decisions of the per-observation tables)."""
        return (self.snooping or SnoopingOptions()).w_test_level

    @classmethod
    def _field_from_dict(cls, name: str, value):
        if value is None:
            return None
        return _CONCERNS[name].from_dict(value)
