"""tlsjax's jit: the engine's XLA options at the top level, a plain nested jit inside a caller's
transformation, the same numbers either way.

Private imports: tlsjax's jit wrapper is a private mechanism; its properties are tested
directly, as those of Monte Carlo's background computation (``_InBackground``).
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tlsjax import _jit
from tlsjax._jit import PREFERRED_OPTIONS, QUICK_OPTIONS, compiler_options, jit

pytestmark = pytest.mark.internal


@functools.partial(jit, static_argnums=1)
def _f(x, k):
    return jnp.sin(x) ** k + jnp.cumsum(x)


def test_options_are_the_preferred_ones_this_jaxlib_accepts(monkeypatch):
    opts = compiler_options()
    assert set(opts) <= set(PREFERRED_OPTIONS)
    assert all(opts[k] == PREFERRED_OPTIONS[k] for k in opts)
    quick = compiler_options(quick=True)
    assert quick == {**opts, **QUICK_OPTIONS}  # this jaxlib knows the optimisation level
    # An option this jaxlib does not know is dropped, the others kept.
    monkeypatch.setattr(_jit, "PREFERRED_OPTIONS", {**PREFERRED_OPTIONS, "xla_no_such_option": 1})
    compiler_options.cache_clear()
    try:
        assert compiler_options() == opts and compiler_options(quick=True) == quick
    finally:
        compiler_options.cache_clear()


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


# The same numbers at XLA's backend optimisation level 0 (the docs build's, the notebooks'
# test's): the engine's point Jacobian as the adjustment computes it, ``x = R (X - S)`` written
# out as products of slices (``matvec_t``), then ``d sph / d x`` by jacfwd, compiled with
# tlsjax's options, against the closed form. With ``hypot`` in ``spherical_from_cartesian``
# the older emitters generated wrong code there: 33 of 1296 entries (elevation rows) off by up
# to 100 %, and an adjustment of the docs did not converge (jaxlib 0.10.2).
_LEVEL0_SCRIPT = """
import json, numpy as np, jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
from tlsjax._jit import compiler_options
from tlsjax._linalg import matvec_t
from tlsjax._model._geometry import spherical_from_cartesian
rng = np.random.default_rng(0)
R = rng.normal(size=(144, 3, 3))
d = rng.normal(size=(144, 3)) * 5
f = lambda R, d: jax.vmap(jax.jacfwd(spherical_from_cartesian))(matvec_t(R, d))
J = jax.jit(f, compiler_options=compiler_options())(R, d)
print(json.dumps(np.asarray(J).tolist()))
"""


def test_point_jacobian_right_at_backend_optimisation_level_0():
    import json
    import os
    import subprocess
    import sys

    env = dict(os.environ, XLA_FLAGS="--xla_backend_optimization_level=0", JAX_PLATFORMS="cpu")
    proc = subprocess.run(
        [sys.executable, "-c", _LEVEL0_SCRIPT], capture_output=True, text=True, env=env, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    J = np.array(json.loads(proc.stdout))
    rng = np.random.default_rng(0)
    R, d = rng.normal(size=(144, 3, 3)), rng.normal(size=(144, 3)) * 5
    x, y, z = np.einsum("mki,mk->mi", R, d).T
    h2, r2 = x**2 + y**2, x**2 + y**2 + z**2
    h, r = np.sqrt(h2), np.sqrt(r2)
    want = np.stack(
        [
            np.stack([x / r, y / r, z / r], -1),  # range
            np.stack([-y / h2, x / h2, 0 * x], -1),  # horizontal direction
            np.stack([-x * z / (r2 * h), -y * z / (r2 * h), h / r2], -1),  # elevation
        ],
        axis=1,
    )
    np.testing.assert_allclose(J, want, rtol=1e-10, atol=1e-12 * np.abs(want).max())


def test_a_result_computed_in_the_background_has_its_shapes_at_once():
    """Monte Carlo's design factorisation is compiled in a background thread while the chunk
    program is compiled on its shapes (``tlsjax._simulation._montecarlo._InBackground``): the
    shapes are those of the value, the value that of a direct call, and an error raised in the
    thread is raised where the value is asked for."""
    from tlsjax._simulation._montecarlo import _InBackground

    x = jnp.linspace(0.0, 1.0, 7)
    fun = jit(lambda: {"a": jnp.cumsum(x) ** 2, "n": jnp.sum(x > 0.5)})
    pending = _InBackground(fun)
    assert pending.shapes["a"].shape == (7,) and pending.shapes["n"].shape == ()
    out = pending.result()
    np.testing.assert_array_equal(out["a"], np.cumsum(np.asarray(x)) ** 2)
    assert int(out["n"]) == 3

    calls = []

    def fails():  # traced by eval_shape, fails when run
        calls.append(1)
        if len(calls) > 1:
            raise RuntimeError("no factorisation")
        return jnp.zeros(())

    broken = _InBackground(fails)
    with pytest.raises(RuntimeError, match="no factorisation"):
        broken.result()
