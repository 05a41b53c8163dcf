import os

import jax
from hypothesis import HealthCheck, Phase, settings

# float64 everywhere (SPEC section 1); tlsjax sets it too, but tests may import jax first.
jax.config.update("jax_enable_x64", True)

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
