"""Strict, atomic JSON files and output paths checked before any work is done.

Every JSON file tlsjax writes goes through :func:`write_json_file`: values are converted to
plain JSON types, NaN and infinities become ``null`` (undefined), ``json`` is called with
``allow_nan=False`` as a last guard, and the text is written to a temporary file in the target
folder that then replaces the target (``os.replace`` is atomic on one file system), so a reader
never sees half a file and a failure leaves the previous file, if any, untouched.
"""

from __future__ import annotations

import json

from .._summary import to_json_value  # noqa: F401  (the one conversion; imported from here)
from ._outputs import (  # noqa: F401  (re-exported: the CLI modules import them from here)
    check_output_dir,
    check_output_file,
    make_parent,
    write_text_atomic,
)


def dumps_strict(obj, indent: int = 2) -> str:
    """Strict JSON text of :func:`to_json_value` (``allow_nan=False``)."""
    return json.dumps(to_json_value(obj), indent=indent, allow_nan=False) + "\n"


def write_json_file(path, obj, option: str = "") -> dict:
    """Write ``obj`` as strict JSON (NaN/inf -> null), atomically; returns what was written."""
    value = to_json_value(obj)
    text = json.dumps(value, indent=2, allow_nan=False) + "\n"
    write_text_atomic(path, text, option)
    return value


#: The other JSON files tlsjax writes, told from a calibration result (which has "result") by
#: their keys: (name, test, description).
_OTHER_KINDS = (
    ("montecarlo", ("runs", "successful"), "a Monte Carlo summary (tlsjax montecarlo --json)"),
    ("compare", ("p_value", "compatible"), "an AP-set compatibility test (tlsjax compare --json)"),
    ("design", ("criterion", "start_value"), "a design optimisation (tlsjax design --json)"),
    ("truth", ("targets", "eops", "units"), "the truth of a simulation (tlsjax simulate --truth)"),
)
_AP_NUMBERS = ("value", "sigma", "t", "max_abs_corr")
_TOP_NUMBERS = ("sigma0", "dof", "n_observations", "n_unknowns", "iterations", "result")
_TOP_MAPPINGS = ("eops", "redundancy", "scanner", "global_test", "planes", "reliability")
_TOP_LISTS = ("outliers", "not_estimable", "weakly_determined", "rank_deficient")


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def json_kind(doc) -> str:
    """ "result" (a calibration), "target check", or one of the names of :data:`_OTHER_KINDS`;
    "unknown" for anything else."""
    if not isinstance(doc, dict):
        return "unknown"
    if "result" in doc:
        return "result"
    if doc.get("kind") == "target check":
        return "target check"
    for name, keys, _ in _OTHER_KINDS:
        if all(k in doc for k in keys):
            return name
    return "unknown"


def check_result_doc(doc, source, accept=()) -> str:
    """The contract fields of a result JSON (SPEC section 11) have their JSON types: each AP an
    object whose value, sigma, t and max_abs_corr are numbers or null (a plain number in a
    simulation's truth); one-line ValueError. ``accept``: other kinds that carry an AP set and
    may be read too ("truth", "target check"). Returns the kind."""
    if not isinstance(doc, dict):
        raise ValueError(
            f"{source}: not a tlsjax result JSON (the top level is a {type(doc).__name__}, "
            "not an object)"
        )
    kind = json_kind(doc)
    described = {name: text for name, _, text in _OTHER_KINDS}
    described["target check"] = "a target check (tlsjax check-targets --json)"
    if kind in described and kind not in accept:
        raise ValueError(
            f"{source}: {described[kind]}, not a calibration result; give the JSON that "
            "`tlsjax calibrate --json` writes"
        )
    if not isinstance(doc.get("aps"), dict):
        raise ValueError(f"{source}: not a tlsjax result JSON (no 'aps' object)")
    for name, entry in doc["aps"].items():
        if kind == "truth" and _is_number(entry):
            continue
        if not isinstance(entry, dict):
            raise ValueError(
                f"{source}: AP {name}: expected an object with value, sigma, unit, got {entry!r}"
            )
        for key in _AP_NUMBERS:
            v = entry.get(key)
            if v is not None and not _is_number(v):
                raise ValueError(f"{source}: AP {name}: {key} is not a number or null ({v!r})")
    for key in _TOP_NUMBERS:
        v = doc.get(key)
        if v is not None and not _is_number(v):
            raise ValueError(f"{source}: '{key}' is not a number or null ({v!r})")
    names, cov = doc.get("ap_covariance_names"), doc.get("ap_covariance")
    if names is not None and not (
        isinstance(names, list) and all(isinstance(n, str) for n in names)
    ):
        raise ValueError(f"{source}: 'ap_covariance_names' must be a list of AP names")
    if cov is not None and not (
        isinstance(cov, list)
        and all(isinstance(r, list) and len(r) == len(cov) for r in cov)
        and all(v is None or _is_number(v) for r in cov for v in r)
        and (names is None or len(names) == len(cov))
    ):
        raise ValueError(
            f"{source}: 'ap_covariance' must be a square matrix of numbers or null, one row per "
            "name in 'ap_covariance_names'"
        )
    for keys, want in ((_TOP_MAPPINGS, dict), (_TOP_LISTS, list)):
        for key in keys:
            v = doc.get(key)
            if v is not None and not isinstance(v, want):
                raise ValueError(
                    f"{source}: '{key}' must be a JSON {'object' if want is dict else 'array'}, "
                    f"got {type(v).__name__}"
                )
    return kind


def read_result_json(source, *, accept=()) -> dict:
    """A tlsjax result JSON as a dict; a one-line ValueError naming the file otherwise (not
    JSON, another kind of tlsjax JSON unless in ``accept``, a contract field of the wrong
    type)."""
    try:
        with open(source, encoding="utf-8") as fh:
            doc = json.load(fh)
    except FileNotFoundError:
        raise
    except IsADirectoryError:
        raise ValueError(f"{source}: is a directory, not a result JSON") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ValueError(f"{source}: not a readable result JSON ({err})") from None
    except RecursionError:
        raise ValueError(f"{source}: not a readable result JSON (nested too deeply)") from None
    check_result_doc(doc, source, accept)
    return doc


def write_json(result, path) -> dict:
    """Write ``result.to_dict()`` (any tlsjax result: a :class:`tlsjax.SelfCalibration`, a
    :class:`tlsjax.CalibrationResult`, ...; or a dict as it is) as strict JSON (NaN and
    infinities are null), atomically: the file is complete or not written. A path that cannot
    be written is a one-line ValueError naming it. Returns the dict written."""
    return write_json_file(path, result if isinstance(result, dict) else result.to_dict())
