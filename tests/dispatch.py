"""Counting the JAX programs executed from the host: what the "nothing eager" rule (GUIDE,
issue 37) is checked with.

Every execution of a compiled program, whether a ``jax.jit`` function or one primitive
dispatched eagerly (``jnp.sin(x)`` outside ``jit`` compiles and runs a one-primitive program),
runs a ``pxla.ExecuteReplicated``. A call that hits jit's C++ fast path never reaches Python,
so while counting the fast path is switched off (``pjit._get_fastpath_data`` returns None)
and the C++ caches are emptied: every execution then passes through ``ExecuteReplicated
.__call__``, which is wrapped to record the program's name. The compiled executables
themselves stay cached, so nothing recompiles.
"""

import collections
import contextlib

import jax
from jax import monitoring
from jax._src import pjit
from jax._src.interpreters import pxla


@contextlib.contextmanager
def executed_programs():
    """Yields a ``collections.Counter`` of the names of the programs executed inside the
    block (one count per execution)."""
    counts = collections.Counter()
    original_call = pxla.ExecuteReplicated.__call__
    original_fastpath = pjit._get_fastpath_data

    def call(self, *args):
        counts[self.name] += 1
        return original_call(self, *args)

    pxla.ExecuteReplicated.__call__ = call
    pjit._get_fastpath_data = lambda *a, **k: None
    _clear_fast_paths()
    try:
        yield counts
    finally:
        pxla.ExecuteReplicated.__call__ = original_call
        pjit._get_fastpath_data = original_fastpath
        _clear_fast_paths()


def _clear_fast_paths():
    # The global caches of jit's C++ dispatch (``clear_all`` alone leaves these two, measured
    # with jax 0.10: an eager vmap then ran unseen), as ``jax.clear_caches`` empties them.
    pjit._cpp_pjit_cache_fun_only.clear()
    pjit._cpp_pjit_cache_explicit_attributes.clear()
    jax._src.lib._jax.PjitFunctionCache.clear_all()


@contextlib.contextmanager
def compiled_programs():
    """Yields a ``collections.Counter`` of the programs compiled inside the block (an XLA
    compile, or an executable read back from the persistent cache: either is a new program)."""
    counts = collections.Counter()

    def on(event, seconds, fun_name=None, **_):
        if event == "/jax/core/compile/backend_compile_duration":
            counts[fun_name] += 1

    monitoring.register_event_duration_secs_listener(on)
    try:
        yield counts
    finally:
        monitoring.unregister_event_duration_listener(on)
