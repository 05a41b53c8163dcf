"""Registry of additional parameters (APs): Chow et al. 2013 eqs. (4)-(6), Lichti & Licht 2006.

Every AP is one coefficient times one basis function of the observations (rho, theta, alpha)
in one observation group. The correction of group g is ``Delta_g = sum_k c_k b_k(l)`` over the
active terms of that group, evaluated at the observations ``l`` (SPEC section 3). Built-in and
user-registered terms go through the same table, so they behave identically.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax.numpy as jnp
import numpy as np

GROUPS = ("range", "hz", "el")
GROUP_INDEX = {g: i for i, g in enumerate(GROUPS)}

# Coefficient units: "m" -> mm in reports, "rad" -> arc seconds, "1" -> ppm.
_UNITS = ("m", "rad", "1")


@dataclasses.dataclass(frozen=True)
class APTerm:
    """One additional parameter: ``correction[group] += coefficient * basis(rho, theta, alpha, scanner)``.

    ``basis`` takes arrays rho, theta, alpha and the :class:`Scanner` settings and returns an
    array of the same shape. ``unit`` is the SI unit of the coefficient ("m", "rad" or "1").
    """

    name: str
    group: str
    basis: Callable
    unit: str
    description: str = ""


_REGISTRY: dict[str, APTerm] = {}


def register_ap(
    name: str,
    group: str,
    basis: Callable,
    unit: str,
    description: str = "",
    *,
    overwrite: bool = False,
) -> APTerm:
    """Register an empirical AP term; it then behaves exactly like the built-in ones.

    ``basis(rho, theta, alpha, scanner)`` must be written with ``jax.numpy`` so that it can be
    traced and differentiated.
    """
    if not isinstance(name, str) or not name.strip() or any(c.isspace() for c in name):
        raise ValueError(f"AP name {name!r} must be a non-empty string without spaces")
    if group not in GROUP_INDEX:
        raise ValueError(f"AP {name}: group {group!r} is not one of {GROUPS}")
    if unit not in _UNITS:
        raise ValueError(
            f"AP {name}: unit {unit!r} is not one of {_UNITS} (coefficient unit in SI)"
        )
    if name in _REGISTRY and not overwrite:
        raise ValueError(f"AP {name} is already registered; pass overwrite=True to replace it")
    if not callable(basis):
        raise ValueError(f"AP {name}: basis must be callable (rho, theta, alpha, scanner) -> array")
    term = APTerm(name, group, basis, unit, description)
    _REGISTRY[name] = term
    return term


def get_ap(name: str) -> APTerm:
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(
            f"unknown AP {name!r}; known terms: {' '.join(sorted(_REGISTRY, key=_sort_key))}"
        ) from None


def registered_aps() -> tuple[str, ...]:
    return tuple(sorted(_REGISTRY, key=_sort_key))


def _sort_key(name: str):
    head = name.rstrip("0123456789")
    tail = name[len(head) :]
    return (head, int(tail) if tail else -1)


def _sec(a):
    return 1.0 / jnp.cos(a)


def _collimation(rho, theta, alpha, scanner):
    # Hybrid scanners observe in one face only; sec(alpha) - 1 removes the part of the
    # collimation error that a rotation about the vertical axis (kappa) absorbs exactly
    # (Chow et al. 2013, note to eq. 5, the "reduced" model).
    return _sec(alpha) - 1.0 if scanner.architecture == "hybrid" else _sec(alpha)


def _U(scanner):
    return scanner.unit_length


def _U2(scanner):
    return scanner.unit_length_2


_BUILTIN = [
    # Chow et al. 2013, eq. (4): range.
    ("A0", "range", lambda r, t, a, s: jnp.ones_like(r), "m", "rangefinder offset"),
    ("A1", "range", lambda r, t, a, s: r, "1", "range scale error (needs scale bars or control)"),
    ("A2", "range", lambda r, t, a, s: jnp.sin(a), "m", "laser axis vertical offset"),
    ("A3", "range", lambda r, t, a, s: jnp.sin(4 * np.pi * r / _U(s)), "m", "cyclic error (sine)"),
    (
        "A4",
        "range",
        lambda r, t, a, s: jnp.cos(4 * np.pi * r / _U(s)),
        "m",
        "cyclic error (cosine)",
    ),
    # Eq. (5): horizontal direction.
    ("B1", "hz", lambda r, t, a, s: t, "1", "horizontal direction scale error"),
    ("B2", "hz", lambda r, t, a, s: jnp.sin(t), "rad", "horizontal circle eccentricity (sine)"),
    ("B3", "hz", lambda r, t, a, s: jnp.cos(t), "rad", "horizontal circle eccentricity (cosine)"),
    (
        "B4",
        "hz",
        lambda r, t, a, s: jnp.sin(2 * t),
        "rad",
        "non-orthogonality of encoder and vertical axis (sine)",
    ),
    (
        "B5",
        "hz",
        lambda r, t, a, s: jnp.cos(2 * t),
        "rad",
        "non-orthogonality of encoder and vertical axis (cosine)",
    ),
    ("B6", "hz", _collimation, "rad", "collimation axis error"),
    ("B7", "hz", lambda r, t, a, s: jnp.tan(a), "rad", "trunnion axis error"),
    ("B8", "hz", lambda r, t, a, s: 1.0 / r, "m", "horizontal eccentricity of collimation axis"),
    ("B9", "hz", lambda r, t, a, s: jnp.sin(a), "rad", "trunnion axis wobble (sine)"),
    ("B10", "hz", lambda r, t, a, s: jnp.cos(a), "rad", "trunnion axis wobble (cosine)"),
    # Eq. (6): elevation angle.
    ("C0", "el", lambda r, t, a, s: jnp.ones_like(a), "rad", "vertical circle index error"),
    ("C1", "el", lambda r, t, a, s: a, "1", "vertical scale error"),
    ("C2", "el", lambda r, t, a, s: jnp.sin(a), "rad", "vertical circle eccentricity (sine)"),
    ("C3", "el", lambda r, t, a, s: jnp.cos(a), "rad", "vertical circle eccentricity (cosine)"),
    (
        "C4",
        "el",
        lambda r, t, a, s: jnp.sin(2 * a),
        "rad",
        "non-orthogonality of vertical encoder and trunnion axis (sine)",
    ),
    (
        "C5",
        "el",
        lambda r, t, a, s: jnp.cos(2 * a),
        "rad",
        "non-orthogonality of vertical encoder and trunnion axis (cosine)",
    ),
    ("C6", "el", lambda r, t, a, s: 1.0 / r, "m", "vertical eccentricity of collimation axis"),
    ("C7", "el", lambda r, t, a, s: jnp.sin(t), "rad", "vertical axis wobble (sine)"),
    ("C8", "el", lambda r, t, a, s: jnp.cos(t), "rad", "vertical axis wobble (cosine)"),
    # Lichti & Licht 2006 empirical terms (names are tlsjax's, SPEC section 3).
    (
        "A5",
        "range",
        lambda r, t, a, s: jnp.sin(4 * np.pi * r / _U2(s)),
        "m",
        "second cyclic error (sine)",
    ),
    (
        "A6",
        "range",
        lambda r, t, a, s: jnp.cos(4 * np.pi * r / _U2(s)),
        "m",
        "second cyclic error (cosine)",
    ),
    (
        "A7",
        "range",
        lambda r, t, a, s: jnp.sin(4 * t),
        "m",
        "range vs horizontal direction, 90 deg period (sine)",
    ),
    (
        "A8",
        "range",
        lambda r, t, a, s: jnp.cos(4 * t),
        "m",
        "range vs horizontal direction, 90 deg period (cosine)",
    ),
    (
        "B11",
        "hz",
        lambda r, t, a, s: jnp.sin(3 * a),
        "rad",
        "horizontal direction vs elevation, 120 deg period",
    ),
    (
        "B12",
        "hz",
        lambda r, t, a, s: jnp.sin(4 * a),
        "rad",
        "horizontal direction vs elevation, 90 deg period",
    ),
    (
        "C9",
        "el",
        lambda r, t, a, s: jnp.sin(3 * t),
        "rad",
        "elevation vs horizontal direction, 120 deg period (sine)",
    ),
    (
        "C10",
        "el",
        lambda r, t, a, s: jnp.cos(3 * t),
        "rad",
        "elevation vs horizontal direction, 120 deg period (cosine)",
    ),
]
for _name, _group, _basis, _unit, _desc in _BUILTIN:
    register_ap(_name, _group, _basis, _unit, _desc)

#: Named AP sets. "chow2013" is the full 24-term model of Chow et al. 2013 eqs. (4)-(6).
PRESETS: dict[str, tuple[str, ...]] = {
    "none": (),
    "physical": ("A0", "B6", "B7", "C0"),
    "chow2013": tuple(f"A{i}" for i in range(5))
    + tuple(f"B{i}" for i in range(1, 11))
    + tuple(f"C{i}" for i in range(9)),
    "chow2013-noscale": ("A0",)
    + tuple(f"A{i}" for i in range(2, 5))
    + tuple(f"B{i}" for i in range(1, 11))
    + tuple(f"C{i}" for i in range(9)),
    "lichti2006": (
        "A0",
        "A1",
        "A3",
        "A4",
        "A5",
        "A6",
        "A7",
        "A8",
        "B6",
        "B7",
        "B11",
        "B12",
        "C0",
        "C9",
        "C10",
    ),
}


def resolve_aps(aps) -> tuple[str, ...]:
    """Turn ``"A0 B6 B7 C0"``, ``"physical"``, ``["A0", "C0"]`` or a mix into a tuple of names.

    Order is kept, duplicates are rejected, unknown names raise ``ValueError``.
    """
    if aps is None:
        return ()
    if isinstance(aps, str):
        tokens = aps.replace(",", " ").split()
    else:
        tokens = [str(a) for a in aps]
    names: list[str] = []
    for tok in tokens:
        expanded = PRESETS.get(tok, (tok,))
        for name in expanded:
            get_ap(name)
            if name in names:
                raise ValueError(f"AP {name} is listed twice in {aps!r}")
            names.append(name)
    return tuple(names)


def ap_corrections(coefficients, names: tuple[str, ...], l, scanner):
    """Corrections ``(Delta rho, Delta theta, Delta alpha)`` at observations ``l[..., 3]``.

    ``coefficients[..., k]`` belongs to ``names[k]``. Chow et al. 2013, eqs. (4)-(6).
    """
    rho, theta, alpha = l[..., 0], l[..., 1], l[..., 2]
    out = [jnp.zeros_like(rho) for _ in GROUPS]
    for k, name in enumerate(names):
        term = _REGISTRY[name]
        g = GROUP_INDEX[term.group]
        out[g] = out[g] + coefficients[..., k] * term.basis(rho, theta, alpha, scanner)
    return jnp.stack(out, axis=-1)
