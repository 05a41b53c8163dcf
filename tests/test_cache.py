"""No compile and no tracing on a re-run (issue 37): tlsjax turns on JAX's persistent
compilation cache in TLSJAX_CACHE_DIR for every program, and stores its adjustment programs
traced (:class:`tlsjax._jit.StoredProgram`), keyed on everything they close over. Counts, not
times."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tlsjax as tj
from tlsjax import _jit


def test_the_suite_compiles_into_the_cache_folder_tlsjax_names():
    folder = jax.config.jax_compilation_cache_dir
    if os.environ.get("TLSJAX_CACHE_DIR", "").lower() in ("off", "0", "none", ""):
        pytest.skip("the cache is turned off for this run")
    assert folder == _jit.cache_dir()
    assert jax.config.jax_persistent_cache_min_compile_time_secs == 0.0  # small ones too
    assert _jit.cache_dir().endswith(f"tlsjax-{tj.__version__}")  # keyed on the version


def test_cache_dir_is_off_when_asked(monkeypatch):
    for off in ("off", "0", "none", ""):
        monkeypatch.setenv("TLSJAX_CACHE_DIR", off)
        assert _jit.cache_dir() is None
    monkeypatch.setenv("TLSJAX_CACHE_DIR", "/some/folder")
    assert _jit.cache_dir() == os.path.join("/some/folder", f"tlsjax-{tj.__version__}")


def _counting(traced):
    def program(x, y):
        traced.append(1)
        return {"sum": x + y, "scaled": 2.0 * x}

    return program


def test_a_stored_program_is_loaded_not_traced_by_a_new_instance(tmp_path, monkeypatch):
    monkeypatch.setattr(_jit, "traced_folder", lambda: str(tmp_path))
    x, y = jnp.arange(3.0), np.ones(3)
    first, second = [], []
    out1 = _jit.StoredProgram(_counting(first), ("test program",))(x, y)
    assert len(first) == 1 and len(list(tmp_path.glob("*.bin"))) == 1
    # Another instance, as in a new process: read back, not traced; the same outputs.
    out2 = _jit.StoredProgram(_counting(second), ("test program",))(x, y)
    assert second == []
    np.testing.assert_array_equal(out2["sum"], out1["sum"])
    np.testing.assert_array_equal(out2["scaled"], 2.0 * np.arange(3.0))
    # Another key or other shapes: traced.
    _jit.StoredProgram(_counting(second), ("test program", "other"))(x, y)
    _jit.StoredProgram(_counting(second), ("test program",))(jnp.arange(4.0), np.ones(4))
    assert len(second) == 2 and len(list(tmp_path.glob("*.bin"))) == 3


def test_a_key_without_a_stable_description_is_never_stored(tmp_path, monkeypatch):
    monkeypatch.setattr(_jit, "traced_folder", lambda: str(tmp_path))
    traced = []
    user_function = lambda r: r  # noqa: E731  e.g. a user's own AP basis
    f = _jit.StoredProgram(_counting(traced), ("user term", user_function))
    out = f(jnp.ones(2), jnp.ones(2))
    assert len(traced) == 1 and list(tmp_path.iterdir()) == []
    np.testing.assert_array_equal(out["sum"], 2.0 * np.ones(2))
