import os
import shutil
import tempfile

import jax
import pytest
from hypothesis import HealthCheck, Phase, settings
from strict_json import check_tree

# JAX's persistent compilation cache, which tlsjax turns on at import in TLSJAX_CACHE_DIR
# (tlsjax/_jit.py), in one temporary folder that the pytest workers (they inherit the
# variable) and the notebooks' kernels share: each program compiles once per run, not once per
# worker, and a program that another test compiled from another Python function object (a new
# closure, a new plan of the same shape) is read back instead of compiled. Removed at the end.
# TLSJAX_CACHE_DIR=off compiles everything; a folder of one's own keeps the programs between
# runs of the edit-test loop.
_SUITE_CACHE = None
if "TLSJAX_CACHE_DIR" not in os.environ:
    _SUITE_CACHE = tempfile.mkdtemp(prefix="tlsjax-test-cache-")
    os.environ["TLSJAX_CACHE_DIR"] = _SUITE_CACHE
    # Unbounded: JAX's bounded cache scans the whole folder on every store, and the suite
    # stores some 3,000 programs (a minute of CPU in the scans; tlsjax._jit.CACHE_MAX_BYTES_ENV).
    os.environ.setdefault("TLSJAX_CACHE_MAX_BYTES", "unbounded")

# XLA's backend optimisations (LLVM) take about 40 % of the suite's CPU time and change no
# result beyond rounding, and XLA's newer fusion emitters took twice the CPU time to compile a
# test's own ``jax.jit`` of the reverse-mode adjustment: the suite compiles with
# ``tlsjax._jit.QUICK_COMPILE_FLAGS``, as the notebooks' kernels (which inherit them) and the
# documentation build do. Set before JAX starts its backend (the workers import this first); a
# flag already named in XLA_FLAGS is kept. tests/test_engine.py checks that a calibration with
# XLA's defaults, what a user runs, agrees with the suite's to rounding.
from tlsjax._jit import quick_compile_flags  # noqa: E402  (after the cache's variables)

os.environ["XLA_FLAGS"] = quick_compile_flags(os.environ.get("XLA_FLAGS", ""))


# The edit-test loop: ``./scripts/test -m fast`` runs the tests listed in tests/fast.txt (node
# ids, one a line: every test file's cheapest tests, chosen from a profile of the whole suite
# by ``scripts/suite_profile.py DIR --write-fast``), a few minutes on 2 cores.
_FAST = os.path.join(os.path.dirname(__file__), "fast.txt")


def pytest_configure(config):
    config.addinivalue_line("markers", "fast: in the quick subset of tests/fast.txt (-m fast)")


# Tests that run tlsjax in processes of their own (the documentation's examples, the notebooks'
# kernels): they share the suite's compilation cache, so they run late, when the other tests
# have compiled most of the programs they need (the documentation's examples took 79 s with an
# empty cache and 58 s after the CLI and selection tests, measured 2026-11-28), but not last:
# about a fifth of each worker's share of the tests comes after them, which the other worker
# can take when it runs out (pytest-xdist's worksteal hands each worker one contiguous half of
# the collection and steals from the end).
_LATE = ("tests/test_docs.py::test_docs_build_and_examples", "tests/test_notebooks.py::")
_LATE_AT = 0.8


def _late_order(items):
    late = [[i for i in items if i.nodeid.startswith(prefix)] for prefix in _LATE]
    if not all(late) or len(items) < 20:
        return items  # a selection of the suite: its order as collected
    moved = {id(i) for group in late for i in group}
    rest = [i for i in items if id(i) not in moved]
    half = len(items) // 2 - len(late[0])
    first, second = rest[:half], rest[half:]
    at1, at2 = int(_LATE_AT * len(first)), int(_LATE_AT * len(second))
    return first[:at1] + late[0] + first[at1:] + second[:at2] + late[1] + second[at2:]


def pytest_collection_modifyitems(config, items):
    items[:] = _late_order(items)
    try:
        with open(_FAST) as f:
            fast = {line.strip() for line in f if line.strip() and not line.startswith("#")}
    except OSError:
        return
    for item in items:
        if item.nodeid in fast:
            item.add_marker(pytest.mark.fast)


def pytest_unconfigure(config):
    if _SUITE_CACHE is not None:  # the process that made it (the workers inherited it)
        shutil.rmtree(_SUITE_CACHE, ignore_errors=True)


# float64 everywhere (SPEC section 1); tlsjax sets it too, but tests may import jax first.
jax.config.update("jax_enable_x64", True)


@pytest.fixture(autouse=True)
def _written_json_is_strict(request):
    """Every JSON file a test writes into its ``tmp_path`` is parsed with NaN and Infinity
    rejected (issue 13)."""
    # Asked for here, tmp_path is torn down after this fixture, so it is still there below.
    folder = request.getfixturevalue("tmp_path") if "tmp_path" in request.fixturenames else None
    yield
    if folder is not None:
        check_tree(folder)


@pytest.fixture(scope="session", autouse=True)
def _all_written_json_is_strict(tmp_path_factory):
    """The same for the module- and session-scoped folders (tmp_path_factory), at the end."""
    yield
    check_tree(tmp_path_factory.getbasetemp())


@pytest.fixture(scope="session", autouse=True)
def _temporary_files_in_pytest_tree(tmp_path_factory):
    """Whatever asks the system for a temporary folder during the tests (the CLI's report, a
    notebook kernel, chromium, matplotlib) gets one inside pytest's own temporary tree, which
    pytest manages: nothing is left in the system temporary folder. Tests themselves use
    ``tmp_path``."""
    folder = str(tmp_path_factory.mktemp("system-tmp"))
    before = os.environ.get("TMPDIR"), tempfile.tempdir
    os.environ["TMPDIR"], tempfile.tempdir = folder, folder
    yield
    if before[0] is None:
        os.environ.pop("TMPDIR", None)
    else:
        os.environ["TMPDIR"] = before[0]
    tempfile.tempdir = before[1]


# Property-based tests (tests/test_property_networks.py): derandomised, so that CI draws the same
# designs every run, without a deadline (the first draw of each shape compiles the adjustment)
# without the example database and without shrinking (every draw costs an adjustment, and a
# failing design is printed in full). Each test sets its own max_examples (tests/networks.py:
# examples(), five times as many under TLSJAX_HYPOTHESIS_PROFILE=thorough).
_COMMON = dict(
    derandomize=True,
    deadline=None,
    database=None,
    print_blob=True,
    phases=(Phase.explicit, Phase.generate),
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
settings.register_profile("ci", **_COMMON)
settings.register_profile("thorough", **_COMMON)
settings.load_profile(os.environ.get("TLSJAX_HYPOTHESIS_PROFILE", "ci"))


# --- What the suite spends its time on (TLSJAX_TEST_PROFILE=folder) ----------------------------
# Per test: wall and CPU time, XLA compiles and their seconds, tracing and lowering seconds, persistent
# cache hits, and the asserts that passed (pytest's assertion-pass hook, on with
# ``-o enable_assertion_pass_hook=true``). Each worker writes profile-<worker>.json into the
# folder; ``scripts/test_profile`` sums them per file.
_PROFILE = os.environ.get("TLSJAX_TEST_PROFILE")
_current = {}
_profile = {}

if _PROFILE:
    import json
    import time

    from jax import monitoring

    _EVENTS = {
        "/jax/core/compile/backend_compile_duration": "compile_s",
        "/jax/core/compile/jaxpr_trace_duration": "trace_s",
        "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_s",
        "/jax/compilation_cache/cache_retrieval_time_sec": "cache_read_s",
    }

    def _on_duration(event, seconds, **_):
        key = _EVENTS.get(event)
        if key and _current:
            _current[key] = _current.get(key, 0.0) + seconds
            if key == "compile_s":
                _current["compiles"] = _current.get("compiles", 0) + 1
            if key == "cache_read_s":
                _current["cache_reads"] = _current.get("cache_reads", 0) + 1

    monitoring.register_event_duration_secs_listener(_on_duration)

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(item, nextitem):
        _current.clear()
        _current["asserts"] = 0
        t0, c0 = time.perf_counter(), time.process_time()
        yield
        # CPU seconds of the worker (all its threads): on a loaded machine the wall time says
        # little, the CPU time what the test costs on an idle one.
        _current["wall_s"] = time.perf_counter() - t0
        _current["cpu_s"] = time.process_time() - c0
        _profile[item.nodeid] = dict(_current)
        _current.clear()

    def pytest_assertion_pass(item, lineno, orig, expl):
        if _current:
            _current["asserts"] += 1

    def pytest_sessionfinish(session):
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        os.makedirs(_PROFILE, exist_ok=True)
        with open(os.path.join(_PROFILE, f"profile-{worker}.json"), "w") as f:
            json.dump(_profile, f, indent=1)
