import jax
import pytest
from strict_json import check_tree

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
