"""The conventions of the public types: a result's ``summary()`` is text and its ``to_dict()``
strict JSON; a settings object's ``to_dict()`` is strict JSON that ``from_dict()`` reads back.

Layer 1 (imports nothing of tlsjax). Every public result type answers ``summary()`` with
human-readable text and ``to_dict()`` with strict-JSON data (plain types; NaN and infinities,
undefined values, as None: :func:`finite_or_none`). Every settings object (``...Options``) is a
frozen dataclass of plain fields (:class:`Settings`), so that a result can carry the settings
that made it and be re-run from its own file. Three types returned data from ``summary()`` before
(:class:`~tlsjax.MonteCarloResult` and :class:`~tlsjax.DesignOptimisation` a dict,
:class:`~tlsjax.ExtractedPlanes` a list); their text is a :class:`SummaryText`, which still
answers the old indexing with a :class:`DeprecationWarning`, so that notebooks written against
the old return value keep running for one release.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

SUMMARY_MESSAGE = "summary() returns text now; use to_dict()"


class SummaryText(str):
    """The text of ``summary()``; a ``str`` in every respect but the deprecated data access.

    ``text[key]`` with a str key (old dict) or an int index (old list), and ``keys()``,
    ``items()``, ``get()`` (old dict), warn and return the old value ``data``. Every other use
    (printing, slicing, ``in``, formatting) is plain text.
    """

    def __new__(cls, text: str, data=None):
        self = super().__new__(cls, text)
        self._data = data
        return self

    def _old(self, kind: type, stacklevel: int = 3):
        data = self.__dict__.get("_data")
        if not isinstance(data, kind):
            return None
        warnings.warn(SUMMARY_MESSAGE, DeprecationWarning, stacklevel=stacklevel)
        return data

    def __getitem__(self, key):
        if isinstance(key, str) and isinstance(self.__dict__.get("_data"), dict):
            return self._old(dict)[key]
        if isinstance(key, int) and isinstance(self.__dict__.get("_data"), list):
            return self._old(list)[key]
        return str.__getitem__(self, key)

    def _dict_method(self, name: str):
        data = self._old(dict, stacklevel=4)  # the user's line: keys() -> here -> _old
        if data is None:
            raise AttributeError(f"'SummaryText' object has no attribute {name!r}")
        return data

    def keys(self):
        return self._dict_method("keys").keys()

    def items(self):
        return self._dict_method("items").items()

    def get(self, key, default=None):
        return self._dict_method("get").get(key, default)


def finite_or_none(obj):
    """``obj`` with every non-finite float (NaN, +-inf: undefined) replaced by None; dicts,
    lists and tuples walked (tuples become lists), numpy scalars as Python numbers."""
    if isinstance(obj, dict):
        return {k: finite_or_none(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_or_none(v) for v in obj]
    if hasattr(obj, "item") and getattr(obj, "shape", None) == ():
        obj = obj.item()  # a numpy or 0-d array scalar
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


class Settings:
    """The settings convention: ``to_dict()`` (strict JSON: the fields, tuples as lists) and
    ``from_dict()`` (the fields back; an unknown name is a one-line ValueError naming it). A
    field whose value is itself settings (or None) is written as its dict (or null); subclasses
    whose fields hold other settings types read them back by overriding
    :meth:`_field_from_dict`."""

    def to_dict(self) -> dict:
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            out[f.name] = v.to_dict() if isinstance(v, Settings) else finite_or_none(v)
        return out

    @classmethod
    def from_dict(cls, data: dict):
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
