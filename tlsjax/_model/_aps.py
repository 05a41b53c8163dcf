"""Registry of additional parameters (APs): Chow et al. 2013 eqs. (4)-(6), Lichti & Licht 2006.

Every AP is one coefficient times one basis function of the observations (rho, theta, alpha)
in one observation group. The correction of group g is ``Delta_g = sum_k c_k b_k(l)`` over the
active terms of that group, evaluated at the observations ``l`` (SPEC section 3). Built-in and
user-registered terms go through the same table, so they behave identically.

Compiled code and the registry: basis functions are looked up here when a model is traced, so a
compiled function depends on the registry. Every registration gets a fresh ``token``; a
:class:`~tlsjax.Scanner` keeps the tokens of its terms (part of its equality and hash), and
tlsjax keys its compiled functions on :meth:`Scanner.current`, the Scanner with the tokens the
registry holds at the call (the static spec of an adjustment is built from it). After a term
is replaced (``overwrite=True``) every Scanner that uses it, made before or after, is a new key
and the next call traces with the new basis. Nothing of JAX's own caches is cleared, so a
user's compiled functions survive a registration. The few caches of tlsjax that are keyed on
AP names without a Scanner register a clearing function with :func:`on_reregistration`.
"""

from __future__ import annotations

import dataclasses
import inspect
import itertools
from collections.abc import Callable

import jax
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
    token: int = 0  # unique per registration: a replaced term never compares equal


_REGISTRY: dict[str, APTerm] = {}
_TOKENS = itertools.count(1)
#: Functions that empty a cache of compiled code (called when a term is replaced).
_CACHE_CLEARERS: list[Callable[[], None]] = []


def on_reregistration(clear: Callable[[], None]) -> Callable[[], None]:
    """Register ``clear`` (e.g. ``functools.lru_cache(...).cache_clear``), called whenever a
    registered AP term is replaced: caches of compiled functions that hold AP names without a
    :class:`Scanner` (whose tokens would change the key) must be emptied then."""
    _CACHE_CLEARERS.append(clear)
    return clear


def _invalidate_compiled() -> None:
    # Only tlsjax's caches keyed on AP names without the Scanner's tokens are emptied; JAX's
    # caches are keyed on the tokens (module docstring) and stay.
    for clear in _CACHE_CLEARERS:
        clear()


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
    traced and differentiated; it is checked here (called on sample observations of both
    architectures, traced with :func:`jax.eval_shape` and differentiated), so a wrong basis is
    refused at registration rather than deep inside an adjustment. Replacing a term
    (``overwrite=True``) takes effect at the next call for every :class:`Scanner` that uses it,
    made before or after (see the module docstring); no compiled function of the user's is
    thrown away.
    """
    if not isinstance(name, str) or not name.strip() or any(c.isspace() for c in name):
        raise ValueError(f"AP name {name!r} must be a non-empty string without spaces")
    if name in PRESETS:
        raise ValueError(f"AP name {name!r} is the name of an AP preset; choose another name")
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
    if not isinstance(description, str):
        raise ValueError(
            f"AP {name}: description must be a string, got {type(description).__name__}"
        )
    check_basis(name, basis)
    return _store(APTerm(name, group, basis, unit, description, next(_TOKENS)))


def _store(term: APTerm) -> APTerm:
    replaced = term.name in _REGISTRY
    _REGISTRY[term.name] = term
    if replaced:
        _invalidate_compiled()
    return term


#: Sample observations for :func:`check_basis`: ranges 0.5..60 m, all directions, and
#: elevations away from the zenith (where sec and tan of the built-in terms are unbounded).
_SAMPLE_RHO = np.array([0.5, 1.7, 4.0, 9.3, 21.0, 60.0])
_SAMPLE_THETA = np.array([0.0, 0.9, 2.1, 3.3, 4.6, 6.1])
_SAMPLE_ALPHA = np.array([-1.2, -0.6, -0.1, 0.3, 0.8, 1.3])


@dataclasses.dataclass(frozen=True)
class _ProbeScanner:
    """The settings a basis reads from its scanner argument (those of :class:`Scanner`, with
    its defaults), for probing a basis at registration without the Scanner class, which itself
    resolves names in this registry."""

    architecture: str
    aps: tuple = ()
    unit_length: float = 1.2
    unit_length_2: float = 0.6
    ap_tokens: tuple = ()


def _probe_basis(basis, scanner):
    """The basis at the samples, its abstract output for a (2, 3) batch, and its gradients."""
    args = tuple(jnp.asarray(a) for a in (_SAMPLE_RHO, _SAMPLE_THETA, _SAMPLE_ALPHA))
    out = basis(*args, scanner)
    batch = jax.ShapeDtypeStruct((2, 3), jnp.float64)
    shaped = jax.eval_shape(lambda r, t, a: basis(r, t, a, scanner), batch, batch, batch)
    grads = jax.grad(lambda *l: jnp.sum(basis(*l, scanner)), argnums=(0, 1, 2))(*args)
    return out, shaped, grads


def check_basis(name: str, basis: Callable) -> None:
    """Refuse a basis that cannot serve as an AP term, with a one-line ``ValueError``.

    The basis must accept ``(rho, theta, alpha, scanner)``, return one finite float per
    observation for observation arrays of any shape (checked on samples and under
    :func:`jax.eval_shape` for a 2-d batch), for both architectures, and be differentiable by
    JAX with finite derivatives (the adjustment differentiates the corrections).
    """
    try:
        inspect.signature(basis).bind(1.0, 2.0, 3.0, None)
    except TypeError:
        raise ValueError(
            f"AP {name}: basis must take four arguments (rho, theta, alpha, scanner)"
        ) from None
    except ValueError:  # some builtins have no signature; the calls below check them
        pass
    for arch in ("hybrid", "panoramic"):
        what = f"AP {name}: basis(rho, theta, alpha, scanner) for a {arch} scanner"
        try:
            out, shaped, grads = _probe_basis(basis, _ProbeScanner(arch))
        except Exception as err:  # any failure of user code is reported the same way
            first = str(err).splitlines()[0] if str(err) else ""
            raise ValueError(
                f"{what} fails: {type(err).__name__}: {first} (write it with jax.numpy so that "
                "it can be traced and differentiated)"
            ) from None
        shape = np.shape(out)
        if shape != _SAMPLE_RHO.shape or getattr(shaped, "shape", None) != (2, 3):
            raise ValueError(
                f"{what} returns shape {shape} for {_SAMPLE_RHO.shape[0]} observations; it must "
                "return one value per observation (e.g. jnp.ones_like(rho) for a constant)"
            )
        if not np.issubdtype(np.asarray(out).dtype, np.floating):
            raise ValueError(f"{what} returns {np.asarray(out).dtype} values; they must be floats")
        if not np.all(np.isfinite(np.asarray(out))):
            raise ValueError(f"{what} is not finite at the sample observations")
        if not all(np.all(np.isfinite(np.asarray(g))) for g in grads):
            raise ValueError(f"{what} has non-finite derivatives at the sample observations")


def get_ap(name: str) -> APTerm:
    """The registered AP term ``name`` (its unit, group and basis function), or a one-line
    ValueError listing the known terms."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(
            f"unknown AP {name!r}; known terms: {' '.join(sorted(_REGISTRY, key=_sort_key))}"
        ) from None


def registered_aps() -> tuple[str, ...]:
    """Names of every registered AP term, built-in and user-registered (:func:`register_ap`),
    in table order (A0, A1, ..., B1, ..., C0, ...)."""
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
# The built-in terms are trusted (and checking them would import Scanner before it exists).
for _name, _group, _basis, _unit, _desc in _BUILTIN:
    _store(APTerm(_name, _group, _basis, _unit, _desc, next(_TOKENS)))


# NIST geometric error model of panoramic scanners with a spinning mirror (Muralikrishnan,
# Ferrucci, Sawyer et al. 2015, "Volumetric performance evaluation of a laser scanner based on
# geometric error model", Precision Engineering 40; Muralikrishnan, Wang, Rachakonda & Sawyer
# 2017, "Terrestrial laser scanner geometric error model parameter correlations in the Two-face,
# Length-consistency, and Network methods of self-calibration", Precision Engineering 52). With
# H the horizontal angle, V the zenith angle and R the range, measured = true + error:
#
#   R_m = R + x2 sin V + x10
#   H_m = H + x1z / (R tan V) + x3 / (R sin V) + x5z / tan V + 2 x6 / sin V + x7 / tan V
#           + x8x sin H - x8y cos H + x11a cos 2H - x11b sin 2H
#   V_m = V + x1n cos V / R + x2 cos V / R + x4 + x5n cos V + x9n cos V - x9z sin V
#           + x12a cos 2V - x12b sin 2V
#
# x1n, x1z beam offset; x2 transit offset; x3 mirror offset; x4 vertical index offset; x5n, x5z
# beam tilt; x6 mirror tilt; x7 transit tilt; x8x, x8y horizontal encoder eccentricity; x9n, x9z
# vertical encoder eccentricity; x10 range (zero) offset; x11a, x11b and x12a, x12b second-order
# scale errors of the horizontal and vertical encoders. In tlsjax's terms H = theta and
# V = pi/2 - alpha (both faces: a face-2 elevation in (pi/2, 3pi/2) is a zenith angle in
# (-pi, 0)), so sin V = cos alpha, cos V = sin alpha, 1/tan V = tan alpha, cos 2V = -cos 2alpha,
# sin 2V = sin 2alpha, and Delta alpha = -Delta V. Each term is one coefficient times one basis
# in one group, so x2's elevation part (x2 cos V / R) is carried by x1n, whose basis it shares
# (the estimated x1n is x1n + x2); x7 has x5z's basis and x9n has x5n's, so each pair is one
# estimable quantity: the "nist" preset leaves x7 and x9n out (they are registered for users
# who fix the other of the pair). x6 takes the reduced form 2 (sec alpha - 1) for hybrid
# scanners, as B6 does (the constant part is a rotation about the vertical axis, kappa).
def _mirror_tilt(rho, theta, alpha, scanner):
    return 2.0 * _collimation(rho, theta, alpha, scanner)


_NIST = [
    ("x1n", "el", lambda r, t, a, s: -jnp.sin(a) / r, "m", "NIST beam offset (normal; with x2's el part)"),
    ("x1z", "hz", lambda r, t, a, s: jnp.tan(a) / r, "m", "NIST beam offset (vertical)"),
    ("x2", "range", lambda r, t, a, s: jnp.cos(a), "m", "NIST transit offset"),
    ("x3", "hz", lambda r, t, a, s: _sec(a) / r, "m", "NIST mirror offset"),
    ("x4", "el", lambda r, t, a, s: -jnp.ones_like(a), "rad", "NIST vertical index offset"),
    ("x5n", "el", lambda r, t, a, s: -jnp.sin(a), "rad", "NIST beam tilt (normal)"),
    ("x5z", "hz", lambda r, t, a, s: jnp.tan(a), "rad", "NIST beam tilt (vertical)"),
    ("x6", "hz", _mirror_tilt, "rad", "NIST mirror tilt"),
    ("x7", "hz", lambda r, t, a, s: jnp.tan(a), "rad", "NIST transit tilt (basis of x5z)"),
    ("x8x", "hz", lambda r, t, a, s: jnp.sin(t), "rad", "NIST horizontal encoder eccentricity (x)"),
    ("x8y", "hz", lambda r, t, a, s: -jnp.cos(t), "rad", "NIST horizontal encoder eccentricity (y)"),
    ("x9n", "el", lambda r, t, a, s: -jnp.sin(a), "rad", "NIST vertical encoder eccentricity (n; basis of x5n)"),
    ("x9z", "el", lambda r, t, a, s: jnp.cos(a), "rad", "NIST vertical encoder eccentricity (z)"),
    ("x10", "range", lambda r, t, a, s: jnp.ones_like(r), "m", "NIST range (zero) offset"),
    ("x11a", "hz", lambda r, t, a, s: jnp.cos(2 * t), "rad", "NIST horizontal encoder 2nd-order scale (cos)"),
    ("x11b", "hz", lambda r, t, a, s: -jnp.sin(2 * t), "rad", "NIST horizontal encoder 2nd-order scale (sin)"),
    ("x12a", "el", lambda r, t, a, s: jnp.cos(2 * a), "rad", "NIST vertical encoder 2nd-order scale (cos)"),
    ("x12b", "el", lambda r, t, a, s: jnp.sin(2 * a), "rad", "NIST vertical encoder 2nd-order scale (sin)"),
]  # fmt: skip
for _name, _group, _basis, _unit, _desc in _NIST:
    _store(APTerm(_name, _group, _basis, _unit, _desc, next(_TOKENS)))

# Lichti & Licht 2006 (seed 003), section 3, Tables 1 and 2: 19 APs, a0 a2..a8 b1..b7 c0 c2 c3
# c4 (a1, scale, "is not included in the model since its estimation requires inclusion of an
# independent scale definition"; c1 is not defined), of which a5 and a6 "are excluded from the
# model hereafter": the final model has 17 terms. The paper's symbols in tlsjax's names:
#
#   paper  basis                         tlsjax  paper's explanation
#   a0     1                             A0      rangefinder additive constant
#   a2     sin(alpha)                    A2      sinusoidal range error vs elevation (empirical)
#   a3 a4  sin, cos(4 pi rho / U)        A3 A4   cyclic error, finest unit length U (0.6 m period:
#                                                Scanner.unit_length = 1.2 m, the default)
#   a5 a6  sin, cos(4 pi rho / U2)       A5 A6   cyclic error, median wavelength
#                                                (Scanner.unit_length_2); not in the final model
#   a7 a8  sin, cos(4 theta)             A7 A8   range vs horizontal direction, 90 deg period
#   b1     sec(alpha)                    B6      collimation axis error (hybrid: sec - 1)
#   b2     tan(alpha)                    B7      trunnion axis error
#   b3 b4  sin, cos(2 theta)             B4 B5   non-orthogonality of encoder plane and
#                                                vertical axis
#   b5     theta                         B1      horizontal direction encoder scale error
#   b6 b7  sin(3 alpha), sin(4 alpha)    B11 B12 horizontal direction vs elevation, 120 and
#                                                90 deg periods
#   c0     1                             C0      vertical circle index error
#   c2     sin(alpha)                    C2      vertical eccentricity (sine term only)
#   c3 c4  sin, cos(3 theta)             C9 C10  elevation vs horizontal direction, 120 deg
#
# Chow, Lichti, Glennie & Hartzell 2013 (seeds 000/002): eqs. (4)-(6) are the full model A0-A4,
# B1-B10, C0-C8 (24 terms, B6 reduced to sec(alpha) - 1 for hybrid scanners, the note to eq.
# 5); without an independent scale A1 is left out (23 terms); Tables 1-5 calibrate "the four
# fundamental systematic errors" A0, B6, B7, C0.
_LICHTI2006 = ("A0", "A2", "A3", "A4", "A7", "A8", "B1", "B4", "B5", "B6", "B7", "B11", "B12")
_LICHTI2006 += ("C0", "C2", "C9", "C10")

#: Named AP sets, each exactly a paper's model (see the tables above). "none" is the papers'
#: "without self-calibration" adjustment.
PRESETS: dict[str, tuple[str, ...]] = {
    "none": (),
    "physical": ("A0", "B6", "B7", "C0"),
    "chow2013-fundamental": ("A0", "B6", "B7", "C0"),
    "chow2013": tuple(f"A{i}" for i in range(5))
    + tuple(f"B{i}" for i in range(1, 11))
    + tuple(f"C{i}" for i in range(9)),
    "chow2013-noscale": ("A0",)
    + tuple(f"A{i}" for i in range(2, 5))
    + tuple(f"B{i}" for i in range(1, 11))
    + tuple(f"C{i}" for i in range(9)),
    # The final 17-term model of Lichti & Licht 2006 (Tables 1 and 2 without a5, a6).
    "lichti2006": _LICHTI2006,
    # All 19 terms of Tables 1 and 2 (with the median-wavelength cyclic pair a5, a6).
    "lichti2006-19": _LICHTI2006[:4] + ("A5", "A6") + _LICHTI2006[4:],
    # NIST model (Muralikrishnan et al. 2015, 2017), one term per estimable quantity (see above).
    "nist": tuple(n for n, *_ in _NIST if n not in ("x7", "x9n")),
}


def resolve_aps(aps) -> tuple[str, ...]:
    """Turn ``"A0 B6 B7 C0"``, ``"physical"``, ``["A0", "C0"]`` or a mix into a tuple of names.

    Order is kept, duplicates are rejected, unknown names raise ``ValueError``.

    >>> import tlsjax as tj
    >>> tj.resolve_aps("physical")
    ('A0', 'B6', 'B7', 'C0')
    >>> tj.resolve_aps("A0, A3 A4 physical")
    Traceback (most recent call last):
    ValueError: AP A0 is listed twice in 'A0, A3 A4 physical'
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


def ap_tokens(names) -> tuple[int, ...]:
    """Registration tokens of the terms ``names`` (they change when a term is replaced)."""
    return tuple(get_ap(n).token for n in names)


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


def ap_basis_matrix(names: tuple[str, ...], l, scanner):
    """``dDelta/da`` at observations ``l[..., 3]``: (..., 3, n), column k the basis of
    ``names[k]`` in its group's row, so ``ap_corrections(a, ...) == ap_basis_matrix(...) @ a``.
    Each basis is evaluated once (autodiff of :func:`ap_corrections` with respect to the
    coefficients multiplies every term by every unit vector: n^2 products per observation)."""
    rho, theta, alpha = l[..., 0], l[..., 1], l[..., 2]
    cols = []
    for name in names:
        term = _REGISTRY[name]
        b = term.basis(rho, theta, alpha, scanner)
        g = GROUP_INDEX[term.group]
        cols.append(jnp.stack([b if i == g else jnp.zeros_like(b) for i in range(3)], axis=-1))
    return jnp.stack(cols, axis=-1)


def corrected_observations(coefficients, names: tuple[str, ...], l, scanner):
    """``l - Delta(l)``: the observations with the modelled systematic errors removed, the
    input of the Gauss-Helmert plane condition (SPEC section 4); ``l`` itself without APs."""
    return l - ap_corrections(coefficients, names, l, scanner)
