import os
import tempfile

import jax
import pytest
from hypothesis import HealthCheck, Phase, settings
from strict_json import check_tree

# The CLI turns on JAX's persistent compilation cache for its process; tests call the CLI in
# process, and one long run crashed (SIGSEGV) inside JAX's cache write after that. Tests compile
# without it (test_notebooks.py gives its kernels their own cache folder).
os.environ.setdefault("TLSJAX_CACHE_DIR", "off")

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
