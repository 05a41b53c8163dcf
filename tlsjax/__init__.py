"""tlsjax: terrestrial laser scanner self-calibration in JAX."""

import jax as _jax

# float64 always (SPEC section 1): set before any array is created.
_jax.config.update("jax_enable_x64", True)

from ._adjust import CalibrationModel as CalibrationModel
from ._adjust import CalibrationResult as CalibrationResult
from ._adjust import SolverOptions as SolverOptions
from ._adjust import calibrate as calibrate
from ._aps import PRESETS as PRESETS
from ._aps import register_ap as register_ap
from ._aps import registered_aps as registered_aps
from ._aps import resolve_aps as resolve_aps
from ._models import Scanner as Scanner
from ._network import Network as Network
from ._network import make_network as make_network
from ._simulate import Room as Room
from ._simulate import Simulation as Simulation
from ._simulate import simulate as simulate
from ._solver import RESULT_MESSAGES as RESULT_MESSAGES

__version__ = "0.1.0"
