"""tlsjax: terrestrial laser scanner self-calibration in JAX.

This module only re-exports the public API. The implementation sits in private subpackages,
one per layer. Imports run one way, down this list: a module imports only from the layers
below its own (and from modules of its own subpackage, without circles); nothing imports this
module except the command line.

1. ``_version`` (the version, which imports nothing), then ``_units``, ``_stats``, ``_jit``,
   ``_optional``, ``_summary``, ``_linalg``, ``_pytree``: units and display factors, quantiles
   and the constants derived from them (scipy), the compiler settings and the persistent
   compilation cache (keyed on the version), the optional libraries, the
   ``summary()``/``to_dict()`` convention of the result types and the
   ``to_dict()``/``from_dict()`` one of the settings, the small dense linear algebra that the
   datum and the adjustment share, the base class of the pytrees (parameters, observations,
   states). They import nothing of tlsjax but the version.
2. ``_model``: the mathematics of one observation (geometry, the AP registry, the scanner, the
   point and plane models, levelling, the datum).
3. ``_adjustment``: one adjustment of a network (data and boundary checks, index plan,
   normal equations, solver, quality, result, approximate values, implicit differentiation).
4. ``_simulation`` (networks with a known truth, Monte Carlo) and ``_io`` (files): on
   layers 1-3.
5. ``_inference`` (tests, VCE, snooping, selection, compatibility), ``_design`` (network
   design) and ``_clouds`` (planes and targets from point clouds): on layers 1-4.
6. ``_report``: the per-observation tables (CSV), the plots and the HTML report.
7. ``_workflow``: the one tested entry of a self-calibration (:func:`self_calibrate`) and its
   result, which composes the pipeline of layer 5 with the text and JSON of layer 6.
8. this module (the public API), then ``_cli`` (the command line), which may use everything;
   ``calibrate``, ``compare``, ``montecarlo`` and ``report`` use the public API only.
   tests/test_layers.py holds the code to this.
"""

import jax as _jax

# float64 always (SPEC section 1): set before any array is created. This is process-wide; the
# README says so at the top, since it also changes the default dtype of a user's other JAX code.
_jax.config.update("jax_enable_x64", True)

from ._adjustment._ap_tests import ap_t_tests as ap_t_tests
from ._adjustment._calibrate import Adjustment as Adjustment
from ._adjustment._calibrate import analyze as analyze
from ._adjustment._calibrate import calibrate as calibrate
from ._adjustment._config import CalibrationModel as CalibrationModel
from ._adjustment._config import SolverOptions as SolverOptions
from ._adjustment._config import scanner_settings as scanner_settings
from ._adjustment._implicit import Estimates as Estimates
from ._adjustment._implicit import NetworkInputs as NetworkInputs
from ._adjustment._implicit import differentiable_adjustment as differentiable_adjustment
from ._adjustment._implicit import network_inputs as network_inputs
from ._adjustment._network import Network as Network
from ._adjustment._network import ObservationTable as ObservationTable
from ._adjustment._network import make_network as make_network
from ._adjustment._network import make_plane_network as make_plane_network
from ._adjustment._result import RESULT_MESSAGES as RESULT_MESSAGES
from ._adjustment._result import CalibrationResult as CalibrationResult
from ._adjustment._result import ResultCode as ResultCode
from ._clouds._extract import ExtractionOptions as ExtractionOptions
from ._clouds._extract import extract_planes as extract_planes
from ._clouds._field_check import FieldCheck as FieldCheck
from ._clouds._field_check import FieldCheckOptions as FieldCheckOptions
from ._clouds._field_check import field_check as field_check
from ._clouds._field_check import field_check_centres as field_check_centres
from ._clouds._match import MatchingOptions as MatchingOptions
from ._clouds._match import match_planes as match_planes
from ._clouds._target_match import TargetMatching as TargetMatching
from ._clouds._target_match import TargetMatchingOptions as TargetMatchingOptions
from ._clouds._target_match import match_targets as match_targets
from ._clouds._targets import ExtractedTargets as ExtractedTargets
from ._clouds._targets import TargetExtractionOptions as TargetExtractionOptions
from ._clouds._targets import extract_targets as extract_targets
from ._clouds._targets import extract_targets_from_files as extract_targets_from_files
from ._clouds._thin import DEFAULT_PLANE_SPACING as DEFAULT_PLANE_SPACING
from ._clouds._thin import thin_planes as thin_planes
from ._design._criteria import DesignCriterion as DesignCriterion
from ._design._criteria import criterion_of_result as criterion_of_result
from ._design._criteria import design_criterion as design_criterion
from ._design._criteria import predicted_cofactor as predicted_cofactor
from ._design._design import DesignProblem as DesignProblem
from ._design._design import PlaneDesign as PlaneDesign
from ._design._design import TargetDesign as TargetDesign
from ._design._optimize import DesignOptimisation as DesignOptimisation
from ._design._optimize import DesignSpace as DesignSpace
from ._design._optimize import optimize_design as optimize_design
from ._inference._apset import APSet as APSet
from ._inference._architecture import ArchitectureComparison as ArchitectureComparison
from ._inference._architecture import ArchitectureFit as ArchitectureFit
from ._inference._architecture import compare_architectures as compare_architectures
from ._inference._checkpoints import CheckpointReport as CheckpointReport
from ._inference._checkpoints import TargetCheck as TargetCheck
from ._inference._checkpoints import assess_checkpoints as assess_checkpoints
from ._inference._checkpoints import check_targets as check_targets
from ._inference._compatibility import CompatibilityOptions as CompatibilityOptions
from ._inference._compatibility import CompatibilityResult as CompatibilityResult
from ._inference._compatibility import compatibility_batch as compatibility_batch
from ._inference._compatibility import compatibility_statistic as compatibility_statistic
from ._inference._compatibility import compatibility_test as compatibility_test
from ._inference._crossval import CrossValidation as CrossValidation
from ._inference._crossval import CrossValidationCode as CrossValidationCode
from ._inference._crossval import CrossValidationOptions as CrossValidationOptions
from ._inference._options import ArchitectureCheckOptions as ArchitectureCheckOptions
from ._inference._options import CalibrationOptions as CalibrationOptions
from ._inference._options import ScreeningOptions as ScreeningOptions
from ._inference._options import SnoopingOptions as SnoopingOptions
from ._inference._options import TestOptions as TestOptions
from ._inference._options import VCEOptions as VCEOptions
from ._inference._outcome import Removal as Removal
from ._inference._outcome import VarianceComponent as VarianceComponent
from ._inference._outcome import VCEResult as VCEResult
from ._inference._robust import PlaneScreening as PlaneScreening
from ._inference._robust import PlaneScreeningOptions as PlaneScreeningOptions
from ._inference._run import cross_validate as cross_validate
from ._inference._run import score_tests as score_tests
from ._inference._score import ScoreTest as ScoreTest
from ._inference._score import ScoreTests as ScoreTests
from ._inference._selection import SelectionOptions as SelectionOptions
from ._inference._selection import SelectionResult as SelectionResult
from ._inference._sensitivity import Sensitivity as Sensitivity
from ._inference._sensitivity import ap_sensitivity as ap_sensitivity
from ._io._correct import Calibration as Calibration
from ._io._correct import correct_points as correct_points
from ._io._correct_files import CorrectedScan as CorrectedScan
from ._io._correct_files import correct_point_cloud as correct_point_cloud
from ._io._extracted import ExtractedPlanes as ExtractedPlanes
from ._io._json import read_result_json as read_result_json
from ._io._json import write_json as write_json
from ._io._las import write_las as write_las
from ._io._outputs import check_outputs as check_outputs
from ._io._plane_files import read_extracted_planes as read_extracted_planes
from ._io._plane_files import read_poses as read_poses
from ._io._plane_files import write_extracted_planes as write_extracted_planes
from ._io._ply import write_ply as write_ply
from ._io._point_clouds import PointCloudScan as PointCloudScan
from ._io._point_clouds import PointCloudWarning as PointCloudWarning
from ._io._point_clouds import point_cloud_format as point_cloud_format
from ._io._point_clouds import read_point_clouds as read_point_clouds
from ._io._priors import parse_ap_prior as parse_ap_prior
from ._io._priors import read_ap_priors as read_ap_priors
from ._io._tables import read_network as read_network
from ._io._tables import read_observations as read_observations
from ._io._tables import read_planes as read_planes
from ._io._tables import read_scans as read_scans
from ._io._tables import write_network as write_network
from ._io._tables import write_observations as write_observations
from ._io._tables import write_scans as write_scans
from ._io._target_files import write_target_table as write_target_table
from ._io._target_lists import read_reference as read_reference
from ._io._target_lists import read_target_list as read_target_list
from ._model._aps import PRESETS as PRESETS
from ._model._aps import get_ap as get_ap
from ._model._aps import register_ap as register_ap
from ._model._aps import registered_aps as registered_aps
from ._model._aps import resolve_aps as resolve_aps
from ._model._geometry import angles_from_matrix as angles_from_matrix
from ._model._geometry import cartesian_from_spherical as cartesian_from_spherical
from ._model._geometry import rotation_matrix as rotation_matrix
from ._model._geometry import spherical_from_cartesian as spherical_from_cartesian
from ._model._plausibility import PlausibilityWarning as PlausibilityWarning
from ._model._scanner import Scanner as Scanner
from ._report._html import report_from_json as report_from_json
from ._report._html import write_html_report as write_html_report
from ._report._plots import plot_ap_correlations as plot_ap_correlations
from ._report._plots import plot_monte_carlo as plot_monte_carlo
from ._report._plots import plot_residuals as plot_residuals
from ._report._plots import plot_sensitivity as plot_sensitivity
from ._report._tables import group_records as group_records
from ._report._tables import observation_records as observation_records
from ._report._tables import write_adjusted_targets as write_adjusted_targets
from ._report._tables import write_tables as write_tables
from ._report._target_plots import plot_all_targets as plot_all_targets
from ._report._target_plots import plot_targets as plot_targets
from ._report._target_plots import target_picture_names as target_picture_names
from ._simulation._design import DesignSimulation as DesignSimulation
from ._simulation._design import NetworkDesign as NetworkDesign
from ._simulation._design import RoomPlane as RoomPlane
from ._simulation._design import simulate_design as simulate_design
from ._simulation._montecarlo import MonteCarloOptions as MonteCarloOptions
from ._simulation._montecarlo import MonteCarloResult as MonteCarloResult
from ._simulation._montecarlo import monte_carlo as monte_carlo
from ._simulation._montecarlo import monte_carlo_network as monte_carlo_network
from ._simulation._point_clouds import Board as Board
from ._simulation._point_clouds import CloudDesign as CloudDesign
from ._simulation._point_clouds import PlanarTarget as PlanarTarget
from ._simulation._point_clouds import PointClouds as PointClouds
from ._simulation._point_clouds import SphereTarget as SphereTarget
from ._simulation._point_clouds import place_targets as place_targets
from ._simulation._point_clouds import simulate_point_clouds as simulate_point_clouds
from ._simulation._room import Room as Room
from ._simulation._room import Simulation as Simulation
from ._simulation._room import simulate as simulate
from ._simulation._truth import SimulationTruth as SimulationTruth
from ._stats import global_test as global_test
from ._units import ARCSEC as ARCSEC
from ._units import DEG as DEG
from ._version import __version__ as __version__
from ._workflow._self_calibration import SelfCalibration as SelfCalibration
from ._workflow._self_calibration import self_calibrate as self_calibrate
