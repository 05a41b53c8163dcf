"""The AP registry and compiled code: a re-registered basis is used at once, a bad basis is
refused at registration (issue 13), and a registration leaves the user's own compiled
functions alone (issue 34)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tlsjax as tj


@pytest.fixture(scope="module")
def net():
    return tj.simulate(tj.Room(n_targets=30), aps="A0 B6 B7 C0 B2", seed=3).network


def _fit(net, aps):
    return tj.calibrate(net, tj.CalibrationModel(tj.Scanner(aps=aps)))


def test_reregistered_basis_gives_the_new_result(net):
    # Independent source: the built-in terms B2 = sin(theta) and B5 = cos(2 theta).
    b2, b5 = _fit(net, "A0 B6 B7 C0 B2"), _fit(net, "A0 B6 B7 C0 B5")
    tj.register_ap("Xrereg", "hz", lambda r, t, a, s: jnp.sin(t), "rad", overwrite=True)
    model = tj.CalibrationModel(tj.Scanner(aps="A0 B6 B7 C0 Xrereg"))
    first = tj.calibrate(net, model)
    np.testing.assert_allclose(first.ap_values, b2.ap_values, rtol=1e-9, atol=1e-15)
    tj.register_ap("Xrereg", "hz", lambda r, t, a, s: jnp.cos(2 * t), "rad", overwrite=True)
    # The same model object (its Scanner made before the replacement) and a new one.
    for m in (model, tj.CalibrationModel(tj.Scanner(aps="A0 B6 B7 C0 Xrereg"))):
        again = tj.calibrate(net, m)
        np.testing.assert_allclose(again.ap_values, b5.ap_values, rtol=1e-9, atol=1e-15)
        assert abs(again.ap_values[-1] - first.ap_values[-1]) > 10 * b5.ap_sigmas[-1]
    old = tj.Scanner(aps="Xrereg")
    tj.register_ap("Xrereg", "hz", lambda r, t, a, s: jnp.sin(t), "rad", overwrite=True)
    # The registration token is part of the key; the compiled functions are keyed on the
    # Scanner as registered now.
    assert tj.Scanner(aps="Xrereg") != old and old.current() == tj.Scanner(aps="Xrereg")


def test_registration_keeps_the_users_compiled_functions():
    user = jax.jit(lambda x: jnp.sin(x) * 2.0)
    user(jnp.ones(3))
    assert user._cache_size() == 1
    tj.register_ap("Xkeep", "el", lambda r, t, a, s: jnp.sin(t), "rad", overwrite=True)
    tj.register_ap("Xkeep", "el", lambda r, t, a, s: jnp.cos(t), "rad", overwrite=True)
    assert user._cache_size() == 1


@pytest.mark.parametrize(
    "basis, message",
    [
        (lambda r, t: t, "four arguments"),
        (lambda r, t, a, s: 1.0, r"shape \(\).*one value per observation"),
        (lambda r, t, a, s: np.sin(t), "TracerArrayConversionError.*jax.numpy"),
        (lambda r, t, a, s: jnp.log(a), "not finite"),
        (lambda r, t, a, s: jnp.sqrt(jnp.abs(t - t)), "non-finite derivatives"),
        (lambda r, t, a, s: s.no_such_setting * r, "AttributeError"),
        (lambda r, t, a, s: (r > 1).astype(jnp.int32), "int"),
    ],
)
def test_bad_basis_is_refused_at_registration(basis, message):
    with pytest.raises(ValueError, match="AP Xbad: " + ".*" + message):
        tj.register_ap("Xbad", "hz", basis, "rad")
    assert "Xbad" not in tj.registered_aps()


def test_preset_name_cannot_be_an_ap():
    with pytest.raises(ValueError, match="preset"):
        tj.register_ap("physical", "hz", lambda r, t, a, s: t, "rad")
