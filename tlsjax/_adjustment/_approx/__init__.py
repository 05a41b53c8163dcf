"""Approximate values of a network (:mod:`._approximate`)."""

from ._approximate import approximate as approximate
from ._approximate import approximate_network as approximate_network
from ._approximate import approximate_values as approximate_values
from ._config import ApproxConfig as ApproxConfig
from ._config import Approximation as Approximation
from ._config import Inconsistency as Inconsistency
