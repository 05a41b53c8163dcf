"""The conventions of the public types: a result's ``summary()`` is text and its ``to_dict()``
strict JSON; a settings object's ``to_dict()`` is strict JSON that ``from_dict()`` reads back.

Layer 1 (imports nothing of tlsjax). Every public result type answers ``summary()`` with
human-readable text and ``to_dict()`` with strict-JSON data (plain types; NaN and infinities,
undefined values, as None: :func:`to_json_value`). Every settings object (``...Options``) is a
frozen dataclass of plain fields (:class:`Settings`), so that a result can carry the settings
that made it and be re-run from its own file.
"""

from __future__ import annotations

import dataclasses
import enum
import math

import numpy as np


def to_json_value(obj):
    """``obj`` as plain JSON types: dicts (string keys), lists, str, int, float, bool, None.

    NaN and +-inf (undefined values) become None; numpy scalars and arrays, tuples, enums and
    dataclasses are converted. Anything else is refused with a TypeError (it has no JSON
    meaning).
    """
    if obj is None or isinstance(obj, (str, bool)):
        return obj
    if isinstance(obj, enum.Enum):
        return to_json_value(obj.value)
    if isinstance(obj, (int, np.integer)) and not isinstance(obj, np.bool_):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, (float, np.floating)):
        x = float(obj)
        return x if math.isfinite(x) else None
    if isinstance(obj, np.ndarray):
        # Whole arrays at once: a result's JSON holds arrays of every observation, and the
        # element-wise walk of their lists took most of a re-run's writing time.
        if obj.dtype.kind in "biu" or (obj.dtype.kind == "f" and np.isfinite(obj).all()):
            return obj.tolist()
        if obj.dtype.kind == "f":
            return np.where(np.isfinite(obj), obj, None).tolist()
        return to_json_value(obj.tolist())
    # Plain values in dicts and lists (most of a result file: 80,000 of them in the demo
    # room's) are taken as they are, without a call each.
    if isinstance(obj, dict):
        return {str(k): v if _plain(v) else to_json_value(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [v if _plain(v) else to_json_value(v) for v in obj]
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return to_json_value(dataclasses.asdict(obj))
    raise TypeError(f"cannot write a {type(obj).__name__} to JSON")


def _plain(v) -> bool:
    """A value JSON takes as it is: str, bool, None, a Python int or a finite float."""
    t = type(v)
    return t is str or t is int or t is bool or v is None or (t is float and math.isfinite(v))


class Settings:
    """The settings convention: ``to_dict()`` (strict JSON: the fields, tuples as lists) and
    ``from_dict()`` (the fields back; an unknown name is a one-line ValueError naming it). A
    field whose value is itself settings (or None) is written as its dict (or null); subclasses
    whose fields hold other settings types read them back by overriding
    :meth:`_field_from_dict`."""

    def to_dict(self) -> dict:
        """The settings as a dict of strict JSON (nested settings as their dicts)."""
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            out[f.name] = v.to_dict() if isinstance(v, Settings) else to_json_value(v)
        return out

    @classmethod
    def from_dict(cls, data: dict):
        """The settings from a dict as :meth:`to_dict` writes it (an unknown name is a
        one-line ValueError naming it)."""
        if not isinstance(data, dict):
            raise ValueError(f"{cls.__name__}: expected a JSON object, got {type(data).__name__}")
        names = {f.name: f for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - set(names))
        if unknown:
            raise ValueError(
                f"{cls.__name__}: unknown setting(s) {', '.join(unknown)} "
                f"(known: {', '.join(names)})"
            )
        return cls(**{k: cls._field_from_dict(k, v) for k, v in data.items()})

    @classmethod
    def _field_from_dict(cls, name: str, value):
        """The value of field ``name`` from its JSON form: lists become tuples."""
        return tuple(value) if isinstance(value, list) else value
