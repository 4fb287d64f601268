"""jaxtable: differentiable batch analysis of electric Gough-Stewart (hexapod) test tables.

Importing jaxtable switches JAX to float64 (`jax_enable_x64`): micrometres on metre-scale
legs need it. Lengths are in mm, angles in radians (degrees only in files, CLI and tables).

The package is laid out by capability (see the README's "Layout"): a small flat core (table,
rotation, kinematics, effects, the one model function, forward solve, batched API), and
private sub-packages `_analysis` (tolerances, sensitivities, error and command maps, Monte
Carlo, workspaces, design), `_calibration` (measurements, instruments, simulation, fits, pose
selection, posterior), `_discovery` (diagnose) and `_reports` (Markdown and figure writers).
Everything public is re-exported here.
"""

from importlib.metadata import PackageNotFoundError, version

import jax

jax.config.update("jax_enable_x64", True)

from . import reports  # noqa: E402  (public report writers: jaxtable.reports)
from ._analysis.commandmap import CommandMap, command_map  # noqa: E402
from ._analysis.errormap import ErrorMap, error_map  # noqa: E402
from ._analysis.montecarlo import monte_carlo  # noqa: E402
from ._analysis.sensitivities import paper_error_jacobian, pose_sensitivity  # noqa: E402
from ._analysis.tolerances import (  # noqa: E402
    ToleranceFileError,
    Tolerances,
    load_tolerances,
    save_tolerances,
)
from ._analysis.workspaces import (  # noqa: E402
    Grid,
    PoseList,
    Workspace,
    WorkspaceFileError,
    load_workspace,
    workspace_slice,
)
from ._api import (  # noqa: E402
    ForwardResult,
    actuator_command,
    check_reachable,
    forward,
    forward_solve,
    joint_bend,
    leg_lengths,
    paper_rod_rotation,
    pose_error,
    reachable,
    rod_rotation,
    spiral_extension,
)
from ._batch import batch_mesh, run_batch  # noqa: E402
from ._cache import enable_compilation_cache  # noqa: E402
from ._calibration.fit import Calibration, calibrate, fit, setup  # noqa: E402
from ._calibration.instruments import interferometer, point_tracker, tracker6  # noqa: E402
from ._calibration.measurements import (  # noqa: E402
    DataFileError,
    Measurements,
    load_measurements,
    save_measurements,
)
from ._calibration.model_file import (  # noqa: E402
    FittedModel,
    InstrumentFrames,
    fitted_model,
    load_fitted_model,
    save_fitted_model,
)
from ._calibration.noise import NoiseEstimate, parse_sigma  # noqa: E402
from ._calibration.poses import (  # noqa: E402
    align_pose_errors,
    compare_with_random,
    evaluate_design,
    pose_jacobians,
    select_poses,
)
from ._calibration.posterior import PosteriorResult, posterior, predictive_bands  # noqa: E402
from ._calibration.prior import check as prior_check  # noqa: E402
from ._calibration.simulate import (  # noqa: E402
    perturb_table,
    plan_grid,
    plan_random,
    plan_swing,
    plan_x_line,
    simulate,
)
from ._calibration.validate import Validation, validate  # noqa: E402
from ._context import Context  # noqa: E402
from ._design.criteria import CRITERIA as DESIGN_CRITERIA  # noqa: E402
from ._design.evaluate import Assessment as DesignAssessment  # noqa: E402
from ._design.evaluate import _first_frequency as first_frequency  # noqa: E402
from ._design.evaluate import _stiffness_matrix as stiffness_matrix  # noqa: E402
from ._design.evaluate import assess as assess_design  # noqa: E402
from ._design.evaluate import assess_batch as assess_designs  # noqa: E402
from ._design.evaluate import design_criteria, design_poses  # noqa: E402
from ._design.hardware import Hardware, hardware_for  # noqa: E402
from ._design.optimize import Constraint as DesignConstraint  # noqa: E402
from ._design.optimize import (  # noqa: E402
    DesignOptimum,
    ParetoFront,
    optimize_design,
    pareto_front,
    parse_constraint,
)
from ._design.symmetric import SymmetricDesign, symmetric_table  # noqa: E402
from ._design.variables import Design  # noqa: E402
from ._discovery.diagnose import Diagnosis, diagnose, heldout_rms  # noqa: E402
from ._discovery.dictionary import DiscriminationPlan, discrimination_plan  # noqa: E402
from ._discovery.gp import ResidualGP, residual_gp  # noqa: E402
from ._discovery.power import Power as DetectionPower  # noqa: E402
from ._discovery.power import detection_power  # noqa: E402
from ._discovery.structure import StructureTest, structure_test  # noqa: E402
from ._effects import (  # noqa: E402
    EFFECTS,
    AbstractEffect,
    Backlash,
    Compliance,
    Discovered,
    LeadScale,
    PeriodicLead,
    Rehoming,
    Spiral,
    Thermal,
    default_effects,
    leg_forces,
)
from ._errors import KinematicsError, TableFileError  # noqa: E402
from ._forward import RESULTS, ForwardOptions, platform_radius  # noqa: E402
from ._io import load_model, load_table, reference_table, save_table, table_from_dict  # noqa: E402
from ._params import GEOMETRY  # noqa: E402
from ._realtime import CommandFunction, command_function  # noqa: E402
from ._reports.posterior import corner_plot, plot_bands  # noqa: E402
from ._rotation import (  # noqa: E402
    euler_from_matrix,
    euler_rate_matrix,
    paper_rotation_matrix,
    rotation_log,
    rotation_matrix,
)
from ._table import Table, check_table, replace  # noqa: E402

__all__ = [
    "DESIGN_CRITERIA",
    "Design",
    "DesignAssessment",
    "DesignConstraint",
    "DesignOptimum",
    "Hardware",
    "ParetoFront",
    "SymmetricDesign",
    "WorkspaceFileError",
    "assess_design",
    "assess_designs",
    "design_criteria",
    "design_poses",
    "first_frequency",
    "hardware_for",
    "load_workspace",
    "optimize_design",
    "pareto_front",
    "parse_constraint",
    "stiffness_matrix",
    # core
    "AbstractEffect",
    "Backlash",
    "CommandFunction",
    "Compliance",
    "Context",
    "Discovered",
    "EFFECTS",
    "ForwardOptions",
    "ForwardResult",
    "GEOMETRY",
    "KinematicsError",
    "LeadScale",
    "PeriodicLead",
    "RESULTS",
    "Rehoming",
    "Spiral",
    "Table",
    "TableFileError",
    "Thermal",
    "actuator_command",
    "batch_mesh",
    "check_reachable",
    "check_table",
    "command_function",
    "default_effects",
    "enable_compilation_cache",
    "euler_from_matrix",
    "euler_rate_matrix",
    "forward",
    "forward_solve",
    "joint_bend",
    "leg_forces",
    "leg_lengths",
    "load_model",
    "load_table",
    "paper_rod_rotation",
    "paper_rotation_matrix",
    "platform_radius",
    "pose_error",
    "reachable",
    "reference_table",
    "prior_check",
    "replace",
    "rod_rotation",
    "rotation_log",
    "rotation_matrix",
    "run_batch",
    "save_table",
    "spiral_extension",
    "table_from_dict",
    # analysis
    "CommandMap",
    "ErrorMap",
    "Grid",
    "PoseList",
    "ToleranceFileError",
    "Tolerances",
    "Workspace",
    "command_map",
    "error_map",
    "load_tolerances",
    "monte_carlo",
    "paper_error_jacobian",
    "pose_sensitivity",
    "save_tolerances",
    "symmetric_table",
    "workspace_slice",
    # calibration
    "Calibration",
    "DataFileError",
    "Measurements",
    "PosteriorResult",
    "align_pose_errors",
    "calibrate",
    "compare_with_random",
    "corner_plot",
    "evaluate_design",
    "fit",
    "interferometer",
    "load_measurements",
    "perturb_table",
    "plot_bands",
    "plan_grid",
    "plan_random",
    "plan_swing",
    "plan_x_line",
    "point_tracker",
    "pose_jacobians",
    "posterior",
    "predictive_bands",
    "save_measurements",
    "select_poses",
    "setup",
    "simulate",
    "tracker6",
    "validate",
    "FittedModel",
    "InstrumentFrames",
    "Validation",
    "fitted_model",
    "load_fitted_model",
    "save_fitted_model",
    "NoiseEstimate",
    "parse_sigma",
    # discovery
    "Diagnosis",
    "DetectionPower",
    "StructureTest",
    "detection_power",
    "diagnose",
    "heldout_rms",
    "residual_gp",
    "discrimination_plan",
    "DiscriminationPlan",
    "ResidualGP",
    "structure_test",
    # report writers
    "reports",
]

try:
    __version__ = version("jaxtable")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0+unknown"
