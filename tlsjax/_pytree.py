"""Parameters, observations and solver states as pytrees: frozen dataclasses whose fields are the
pytree's children, except the fields marked static, which are part of its structure.

This is the part of ``equinox.Module`` that tlsjax used (with ``equinox.field(static=True)``
and ``equinox.tree_at``, now :func:`dataclasses.replace`), written here because importing
equinox took about 0.14 s of the 0.8 s that ``import tlsjax`` may take (issue 37): it imports
its neural-network, debugging and serialisation modules with it. The semantics are equinox's:
a module is immutable; two modules are equal when they are of one type with equal fields
(arrays element by element); a module hashes by its fields, so one made of static fields only
(:class:`tlsjax._adjustment._families.Spec`) keys compiled programs by value, and one that
holds arrays is no more hashable than an array.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np


def field(*, static: bool = False, **kwargs):
    """A dataclass field; ``static``: part of the pytree's structure (hashable, compared by
    value when a program is looked up), not a child."""
    metadata = {**kwargs.pop("metadata", {}), "static": static}
    return dataclasses.field(metadata=metadata, **kwargs)


class Module:
    """Base class of tlsjax's pytrees: each subclass becomes a frozen dataclass registered with
    JAX, its non-static fields the children in the order declared."""

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        # eq=False: __eq__ and __hash__ are this class's, for every subclass.
        dataclasses.dataclass(frozen=True, eq=False)(cls)
        fields = dataclasses.fields(cls)
        jax.tree_util.register_dataclass(
            cls,
            data_fields=[f.name for f in fields if not f.metadata.get("static", False)],
            meta_fields=[f.name for f in fields if f.metadata.get("static", False)],
        )

    def __eq__(self, other) -> bool:
        if type(self) is not type(other):
            return NotImplemented
        mine, tree = jax.tree.flatten(self)
        theirs, other_tree = jax.tree.flatten(other)
        if tree != other_tree:
            return False
        return all(_leaf_equal(a, b) for a, b in zip(mine, theirs))

    def __hash__(self) -> int:
        return hash(tuple((f.name, getattr(self, f.name)) for f in dataclasses.fields(self)))


def kept(obj, name: str, make):
    """``make()`` computed once and kept on ``obj``, an immutable object (a frozen dataclass:
    a :class:`Module`, a settings object), under ``name``: later calls return the same value.
    It is no field (neither a pytree child nor part of equality or hash), and
    ``dataclasses.replace`` makes an object without it, as the value may depend on any field."""
    value = obj.__dict__.get(name)
    if value is None:
        value = obj.__dict__[name] = make()
    return value


def _leaf_equal(a, b) -> bool:
    if a is b:
        return True
    if isinstance(a, (np.ndarray, np.generic, jax.Array)) or isinstance(
        b, (np.ndarray, np.generic, jax.Array)
    ):
        a, b = np.asarray(a), np.asarray(b)
        return a.shape == b.shape and a.dtype == b.dtype and bool(np.array_equal(a, b))
    return bool(a == b)
