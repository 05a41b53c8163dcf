"""tlsjax's jit: the engine's XLA options at the top level, a plain nested jit inside a caller's
transformation, the same numbers either way.

Private imports: tlsjax's jit wrapper is a private mechanism; its properties are tested
directly.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tlsjax._jit import PREFERRED_OPTIONS, compiler_options, jit

pytestmark = pytest.mark.internal


@functools.partial(jit, static_argnums=1)
def _f(x, k):
    return jnp.sin(x) ** k + jnp.cumsum(x)


def test_options_are_the_preferred_ones_this_jaxlib_accepts():
    opts = compiler_options()
    assert set(opts) <= set(PREFERRED_OPTIONS)
    assert all(opts[k] == PREFERRED_OPTIONS[k] for k in opts)


def test_same_numbers_at_top_level_and_inside_a_callers_transformations():
    x = jnp.linspace(0.1, 1.0, 7)
    ref = np.sin(np.asarray(x)) ** 3 + np.cumsum(np.asarray(x))
    np.testing.assert_allclose(_f(x, 3), ref, rtol=1e-14)
    np.testing.assert_allclose(_f.lower(x, 3).compile()(x), ref, rtol=1e-14)
    # Inside a caller's jit with a tracer argument, and with only closed-over constants.
    np.testing.assert_allclose(jax.jit(lambda y: _f(y, 3))(x), ref, rtol=1e-14)
    np.testing.assert_allclose(jax.jit(lambda: _f(x, 3))(), ref, rtol=1e-14)
    np.testing.assert_allclose(jax.vmap(lambda y: _f(y, 3))(x[None]), ref[None], rtol=1e-14)
    # Derivative against its closed form: d/dx_i sum(sin^3 + cumsum) = 3 sin^2 cos + (n - i).
    g = jax.grad(lambda y: jnp.sum(_f(y, 3)))(x)
    xs = np.asarray(x)
    want = 3 * np.sin(xs) ** 2 * np.cos(xs) + np.arange(len(xs), 0, -1)
    np.testing.assert_allclose(g, want, rtol=1e-13)


def test_wrapper_keeps_the_function_and_the_cache():
    assert _f.__wrapped__.__name__ == "_f"
    x = jnp.ones(3)
    _f(x, 2)
    n = _f._cache_size()
    _f(x + 1.0, 2)
    assert _f._cache_size() == n
