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
from ._checkpoints import CheckpointReport as CheckpointReport
from ._checkpoints import assess_checkpoints as assess_checkpoints
from ._clouds import Board as Board
from ._clouds import CloudDesign as CloudDesign
from ._clouds import PointClouds as PointClouds
from ._clouds import simulate_point_clouds as simulate_point_clouds
from ._compat import APSet as APSet
from ._compat import CompatibilityOptions as CompatibilityOptions
from ._compat import CompatibilityResult as CompatibilityResult
from ._compat import compatibility_test as compatibility_test
from ._extract import ExtractedPlanes as ExtractedPlanes
from ._extract import ExtractionConfig as ExtractionConfig
from ._extract import MatchingConfig as MatchingConfig
from ._extract import extract_planes as extract_planes
from ._extract import load_planes as load_planes
from ._extract import match_planes as match_planes
from ._extract import save_planes as save_planes
from ._io import read_network as read_network
from ._io import read_observations as read_observations
from ._io import read_planes as read_planes
from ._io import read_scans as read_scans
from ._io import write_observations as write_observations
from ._models import Scanner as Scanner
from ._montecarlo import MonteCarloOptions as MonteCarloOptions
from ._montecarlo import MonteCarloResult as MonteCarloResult
from ._montecarlo import monte_carlo as monte_carlo
from ._montecarlo import monte_carlo_network as monte_carlo_network
from ._network import Network as Network
from ._network import make_network as make_network
from ._network import make_plane_network as make_plane_network
from ._pointclouds import PointCloudScan as PointCloudScan
from ._pointclouds import read_point_clouds as read_point_clouds
from ._plots import plot_ap_correlations as plot_ap_correlations
from ._plots import plot_residuals as plot_residuals
from ._report import ap_table as ap_table
from ._report import global_test as global_test
from ._report import result_to_dict as result_to_dict
from ._report import write_json as write_json
from ._selection import SelectionOptions as SelectionOptions
from ._selection import SelectionResult as SelectionResult
from ._selection import select_aps as select_aps
from ._simulate import Room as Room
from ._simulate import Simulation as Simulation
from ._simulate import simulate as simulate
from ._solver import RESULT_MESSAGES as RESULT_MESSAGES
from ._statistics import TestedCalibration as TestedCalibration
from ._statistics import TestingOptions as TestingOptions
from ._statistics import ap_t_tests as ap_t_tests
from ._statistics import calibrate_and_test as calibrate_and_test

try:
    from importlib.metadata import version as _version

    __version__ = _version("tlsjax")
except Exception:  # pragma: no cover - running from a source tree without metadata
    __version__ = "0.1.0"
