"""Settings of one instrument: architecture, active APs and unit lengths (SPEC sections 1, 3)."""

from __future__ import annotations

import dataclasses

import numpy as np

from ._aps import ap_tokens, resolve_aps

ARCHITECTURES = ("hybrid", "panoramic")


@dataclasses.dataclass(frozen=True)
class Scanner:
    """Settings of one instrument: architecture, active APs and unit lengths.

    ``architecture``: "hybrid" (one face, theta in [0, 2pi), alpha in [-pi/2, pi/2]) or
    "panoramic" (two faces, theta in [0, pi), alpha in [-pi/2, 3pi/2)). ``aps``: names or
    presets, e.g. ``"A0 B6 B7 C0"`` or ``"chow2013"``. ``unit_length`` U [m] of the cyclic
    terms A3/A4, ``unit_length_2`` of A5/A6. ``ap_tokens`` (set here, not an argument) are
    the registration tokens of the APs when the Scanner was made: part of its equality and
    hash, hence of every cache key it enters (the static spec of an adjustment among them).
    :meth:`current` is the Scanner with the tokens of the registry as it is now; tlsjax keys
    its compiled functions on that, so a term re-registered with ``overwrite=True`` is used at
    the next call even through a Scanner made before, and nothing traced with the old basis is
    reused.
    """

    architecture: str = "hybrid"
    aps: tuple = ("A0", "B6", "B7", "C0")
    unit_length: float = 1.2
    unit_length_2: float = 0.6
    ap_tokens: tuple = dataclasses.field(init=False, repr=False, default=())

    def __post_init__(self):
        if self.architecture not in ARCHITECTURES:
            raise ValueError(
                f"scanner architecture {self.architecture!r} is not one of {ARCHITECTURES}"
            )
        object.__setattr__(self, "aps", resolve_aps(self.aps))
        object.__setattr__(self, "ap_tokens", ap_tokens(self.aps))
        for name, u in (("unit_length", self.unit_length), ("unit_length_2", self.unit_length_2)):
            if not (np.isfinite(u) and u > 0):
                raise ValueError(f"scanner {name} must be a positive length in metres, got {u}")

    def current(self) -> Scanner:
        """This Scanner, or a copy with the registration tokens its APs have now if one of
        them was re-registered since it was made."""
        if self.ap_tokens == ap_tokens(self.aps):
            return self
        return dataclasses.replace(self)
