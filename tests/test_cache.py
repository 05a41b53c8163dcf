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
    # The bound read at import: the suite's throw-away folder is unbounded (tests/conftest.py).
    assert jax.config.jax_compilation_cache_max_size == _jit.cache_max_bytes()


def test_cache_dir_is_off_when_asked(monkeypatch):
    for off in ("off", "0", "none", ""):
        monkeypatch.setenv("TLSJAX_CACHE_DIR", off)
        assert _jit.cache_dir() is None
    monkeypatch.setenv("TLSJAX_CACHE_DIR", "/some/folder")
    assert _jit.cache_dir() == os.path.join("/some/folder", f"tlsjax-{tj.__version__}")


def test_cache_bound_from_the_environment(monkeypatch):
    monkeypatch.delenv("TLSJAX_CACHE_MAX_BYTES", raising=False)
    assert _jit.cache_max_bytes() == _jit.CACHE_MAX_BYTES
    for value, bound in (("5e8", 500_000_000), ("unbounded", -1), ("0", -1), ("-3", -1)):
        monkeypatch.setenv("TLSJAX_CACHE_MAX_BYTES", value)
        assert _jit.cache_max_bytes() == bound, value
    monkeypatch.setenv("TLSJAX_CACHE_MAX_BYTES", "1 GB")
    with pytest.warns(UserWarning, match="TLSJAX_CACHE_MAX_BYTES='1 gb' is not a number"):
        assert _jit.cache_max_bytes() == _jit.CACHE_MAX_BYTES


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


def _compiles(events):
    def listen(name, duration, **kwargs):
        if name.endswith("backend_compile_duration"):
            events.append(name)

    return listen


@pytest.mark.parametrize("stored", [True, False])
def test_a_prepared_program_is_compiled_beside_the_next_compile(tmp_path, monkeypatch, stored):
    """:meth:`StoredProgram.prepare` queues the program; the next call of another stored
    program that compiles starts it in the background; the call that needs it compiles
    nothing and gets the same numbers as a program compiled in the foreground."""
    monkeypatch.setattr(_jit, "traced_folder", lambda: str(tmp_path) if stored else None)
    monkeypatch.setattr(_jit, "_QUEUED", [])
    x, y = jnp.arange(5.0) + 0.5, np.linspace(0, 1, 5)
    traced, events = [], []
    later = _jit.StoredProgram(_counting(traced), ("prepared later", stored))
    later.prepare(x, y)
    later.prepare(x, y)  # queued once
    assert traced == [] and len(_jit._QUEUED) == 1
    first = _jit.StoredProgram(lambda a: {"a": a * 3.0}, ("first", stored))
    first(x)  # compiles, and starts the queued one beside it
    assert _jit._QUEUED == []
    for task in list(later._pending.values()):
        task.result()
    assert len(traced) == 1 and later._pending == {}
    listen = _compiles(events)
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        out = later(x, y)
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert events == [] and len(traced) == 1  # neither compiled nor traced again
    np.testing.assert_array_equal(out["sum"], np.asarray(x) + y)
    # Prepared but called before any other compile: the call does the work itself, once.
    alone = _jit.StoredProgram(_counting(traced), ("prepared alone", stored))
    alone.prepare(x, y)
    np.testing.assert_array_equal(alone(x, y)["scaled"], 2.0 * np.asarray(x))
    assert len(traced) == 2 and alone._pending == {} and _jit._QUEUED == []


def test_a_key_without_a_stable_description_is_never_stored(tmp_path, monkeypatch):
    monkeypatch.setattr(_jit, "traced_folder", lambda: str(tmp_path))
    traced = []
    user_function = lambda r: r  # noqa: E731  e.g. a user's own AP basis
    f = _jit.StoredProgram(_counting(traced), ("user term", user_function))
    out = f(jnp.ones(2), jnp.ones(2))
    assert len(traced) == 1 and list(tmp_path.iterdir()) == []
    np.testing.assert_array_equal(out["sum"], 2.0 * np.ones(2))


def test_a_process_killed_mid_store_does_not_stop_later_stores(tmp_path):
    """JAX writes an entry, then its access-time file; a process killed between the two left an
    entry without one, and every later store in the folder failed (a warning per program,
    nothing cached). A new process repairs the folder at import and stores again."""
    import subprocess
    import sys

    folder = tmp_path / f"tlsjax-{tj.__version__}"
    folder.mkdir()
    (folder / "jit_orphan-0123456789abcdef-cache").write_bytes(b"x" * 64)  # no -atime
    program = (
        "import warnings, jax.numpy as jnp, tlsjax\n"
        "warnings.simplefilter('error')\n"  # a failed store warns: fail the run instead
        "print(float(jnp.sin(jnp.arange(3.0)).sum()))\n"
    )
    env = dict(os.environ, TLSJAX_CACHE_DIR=str(tmp_path), JAX_PLATFORMS="cpu")
    env.pop("TLSJAX_CACHE_MAX_BYTES", None)  # the default: bounded, with access-time files
    run = subprocess.run([sys.executable, "-c", program], env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert "Error writing persistent compilation cache" not in run.stderr
    entries = {p.name for p in folder.iterdir()}
    stored = {n for n in entries if n.endswith("-cache")} - {"jit_orphan-0123456789abcdef-cache"}
    assert stored, entries  # the new program was stored
    assert all(n[: -len("cache")] + "atime" in entries for n in entries if n.endswith("-cache"))


def test_quick_compile_flags_add_what_is_not_named():
    assert _jit.quick_compile_flags("") == (
        "--xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false"
    )
    named = "--xla_force_host_platform_device_count=2 --xla_backend_optimization_level=2"
    assert _jit.quick_compile_flags(named) == named + " --xla_cpu_use_fusion_emitters=false"
    # The suite runs with them (tests/conftest.py).
    assert all(f"--{n}=" in os.environ["XLA_FLAGS"] for n in _jit.QUICK_COMPILE_FLAGS)
