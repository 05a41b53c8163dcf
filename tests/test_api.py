"""The public API as a user holds it: settings objects are called ``Options``, and the names of
earlier releases still resolve, with a DeprecationWarning naming their replacement."""

import pytest

import tlsjax as tj


@pytest.mark.parametrize(
    "old, new", [("ExtractionConfig", "ExtractionOptions"), ("MatchingConfig", "MatchingOptions")]
)
def test_old_names_warn_and_resolve_to_the_new_ones(old, new):
    with pytest.warns(DeprecationWarning, match=f"tlsjax.{new}"):
        obj = getattr(tj, old)
    assert obj is getattr(tj, new)


def test_unknown_names_still_raise_attribute_error():
    with pytest.raises(AttributeError, match="NoSuchThing"):
        _ = tj.NoSuchThing


def test_settings_objects_share_one_word():
    settings = [n for n in dir(tj) if n.endswith(("Config", "Settings", "Params"))]
    assert settings == [], settings
