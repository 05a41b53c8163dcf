"""The pytree base class of tlsjax's parameters, observations and states (issue 37: it replaces
``equinox.Module``, whose import cost 0.14 s).

Private imports: ``tlsjax._pytree`` (a building block) and the adjustment's ``Spec`` and
``Params``, checked against what JAX itself does with their fields.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tlsjax._pytree import Module, field

pytestmark = pytest.mark.internal


class _Pair(Module):
    x: jax.Array
    y: tuple
    name: str = field(static=True, default="a")


class _Triple(_Pair):
    z: jax.Array = None


def test_fields_are_children_and_static_fields_structure():
    p = _Pair(jnp.arange(3.0), (np.ones(2), 1.0), name="b")
    leaves, tree = jax.tree.flatten(p)
    assert len(leaves) == 3 and np.array_equal(leaves[0], np.arange(3.0))
    assert jax.tree.unflatten(tree, leaves) == p
    # The static field is part of the structure: another value is another treedef.
    assert jax.tree.structure(dataclasses.replace(p, name="c")) != tree
    doubled = jax.tree.map(lambda v: v * 2, p)
    assert isinstance(doubled, _Pair) and doubled.name == "b"
    np.testing.assert_array_equal(doubled.y[0], 2 * np.ones(2))
    # A subclass adds its fields after its parent's, and is a pytree of its own.
    t = _Triple(jnp.zeros(1), (), z=jnp.ones(2))
    assert [f.name for f in dataclasses.fields(t)] == ["x", "y", "name", "z"]
    assert len(jax.tree.leaves(t)) == 2


def test_immutable_equal_by_value_and_hashed_by_fields():
    p = _Pair(np.arange(3.0), (2.0,))
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.x = np.zeros(3)
    assert p == _Pair(np.arange(3.0), (2.0,))
    assert p != _Pair(np.arange(3.0) + 1, (2.0,))
    assert p != _Pair(np.arange(3.0), (2.0,), name="c")
    assert p != _Pair(np.arange(4.0), (2.0,))
    with pytest.raises(TypeError):  # arrays are not hashable, nor is what holds them
        hash(p)
    static = _Pair(None, ("u", 1))
    assert hash(static) == hash(_Pair(None, ("u", 1))) and static == _Pair(None, ("u", 1))


def test_a_static_argument_keys_the_compiled_program_by_value():
    traces = []

    @jax.jit
    def f(p):
        traces.append(1)
        return p.x * 2

    f(_Pair(jnp.ones(2), ()))
    f(_Pair(jnp.zeros(2), ()))  # other values, the same structure: no new trace
    assert len(traces) == 1
    f(_Pair(jnp.zeros(2), (), name="z"))  # another static value: traced anew
    assert len(traces) == 2

    g = jax.jit(lambda s, v: v + len(s.y), static_argnums=0)
    g(_Pair(None, ("a", "b")), 1.0)
    g(_Pair(None, ("a", "b")), 2.0)  # an equal spec built anew: the same program
    assert g._cache_size() == 1
