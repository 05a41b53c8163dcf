"""How tlsjax compiles: ``jax.jit`` with the XLA options chosen for this engine, in one place.

XLA's CPU backend has two code generators for fused kernels: the newer MLIR "fusion emitters"
(the default in current jaxlib) and the older LLVM IR emitters. For tlsjax's programs the older
ones compile about twice as fast and without the compiler's memory transient of about 0.5 GB,
while the compiled adjustment runs at the same speed for large networks, planes and Monte Carlo
and 7 % (4 APs) to 20 % (23 APs) slower for the small Chow room (measured 2026-11-24 in one
process, both executables timed alternately; ``benchmarks/README.md``). A self-calibration is
compiled once and run a few times (a CLI call, a notebook cell), so the compile is most of what
a user waits for, and the memory transient set the peak of a plane adjustment: the older
emitters are chosen.

The option is a field of XLA's debug options; a jaxlib without it rejects it when compiling, so
it is tried once, on a trivial function, at the first compile (not at import: the backend must
not start before the user's own XLA settings, e.g. the host device count, are read).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

#: XLA options of every compiled tlsjax function (where this jaxlib knows them).
PREFERRED_OPTIONS = {"xla_cpu_use_fusion_emitters": False}


@functools.cache
def compiler_options() -> dict:
    """The subset of :data:`PREFERRED_OPTIONS` this jaxlib accepts (checked once)."""
    try:
        jax.jit(lambda x: x + 1.0).lower(jnp.zeros(())).compile(compiler_options=PREFERRED_OPTIONS)
    except Exception:  # an older or newer jaxlib without the option: its defaults
        return {}
    return dict(PREFERRED_OPTIONS)


class _Jit:
    """``jax.jit(fun, **kwargs)`` with :func:`compiler_options`, made at the first use."""

    def __init__(self, fun, kwargs):
        functools.update_wrapper(self, fun)
        self._fun, self._kwargs = fun, kwargs

    @functools.cached_property
    def _jitted(self):
        return jax.jit(self._fun, compiler_options=compiler_options(), **self._kwargs)

    @functools.cached_property
    def _nested(self):
        return jax.jit(self._fun, **self._kwargs)

    def __call__(self, *args, **kwargs):
        # Compiler options belong to a top-level compile: inside a caller's jit, grad, jvp or
        # vmap this is a nested jit, compiled (and optimised) with the caller's program.
        if not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((args, kwargs))):
            try:
                return self._jitted(*args, **kwargs)
            except ValueError as exc:  # inside a trace with concrete arguments only
                if "compiler_options" not in str(exc):
                    raise
        return self._nested(*args, **kwargs)

    def __getattr__(self, name):  # lower, trace, eval_shape, _cache_size, ...
        if name.startswith("__") or name in ("_fun", "_kwargs", "_jitted", "_nested"):
            raise AttributeError(name)
        return getattr(self._jitted, name)


def jit(fun=None, **kwargs):
    """``jax.jit`` with tlsjax's compiler options; usable as ``@jit`` or
    ``@functools.partial(jit, static_argnums=...)``."""
    if fun is None:
        return functools.partial(jit, **kwargs)
    return _Jit(fun, kwargs)
