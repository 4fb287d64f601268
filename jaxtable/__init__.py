"""jaxtable: differentiable batch analysis of electric Gough-Stewart (hexapod) test tables.

Importing jaxtable switches JAX to float64 (`jax_enable_x64`): micrometres on metre-scale
legs need it. Lengths are in mm, angles in radians (degrees only in files, CLI and tables).
"""

import jax

jax.config.update("jax_enable_x64", True)

from ._api import (  # noqa: E402
    ForwardResult,
    actuator_command,
    check_reachable,
    forward,
    forward_solve,
    joint_bend,
    leg_lengths,
    paper_rod_rotation,
    reachable,
    rod_rotation,
    spiral_extension,
)
from ._batch import batch_mesh, run_batch  # noqa: E402
from ._calibrate import Calibration, calibrate, fit, setup, validate  # noqa: E402
from ._commandmap import CommandMap, command_map  # noqa: E402
from ._context import Context  # noqa: E402
from ._data import DataFileError, Measurements, load_measurements, save_measurements  # noqa: E402
from ._design import symmetric_table  # noqa: E402
from ._diagnose import Diagnosis, diagnose, heldout_rms  # noqa: E402
from ._effects import (  # noqa: E402
    EFFECTS,
    AbstractEffect,
    Backlash,
    Compliance,
    LeadScale,
    PeriodicLead,
    Rehoming,
    Spiral,
    Thermal,
    default_effects,
    leg_forces,
)
from ._errormap import ErrorMap, Grid, PoseList, error_map, workspace_slice  # noqa: E402
from ._errors import KinematicsError, TableFileError  # noqa: E402
from ._forward import ForwardOptions  # noqa: E402
from ._instrument import interferometer, point_tracker, tracker6  # noqa: E402
from ._io import load_model, load_table, reference_table, save_table, table_from_dict  # noqa: E402
from ._montecarlo import monte_carlo  # noqa: E402
from ._poses import compare_with_random, evaluate_design, pose_jacobians, select_poses  # noqa: E402
from ._posterior import PosteriorResult, corner_plot, plot_bands, posterior, predictive_bands  # noqa: E402
from ._realtime import CommandFunction, command_function  # noqa: E402
from ._rotation import euler_rate_matrix, paper_rotation_matrix, rotation_matrix  # noqa: E402
from ._sensitivity import paper_error_jacobian, pose_sensitivity  # noqa: E402
from ._simulate import perturb_table, plan_grid, plan_random, plan_swing, plan_x_line, simulate  # noqa: E402
from ._table import Table, check_table, replace  # noqa: E402
from ._tolerance import (  # noqa: E402
    ToleranceFileError,
    Tolerances,
    load_tolerances,
    save_tolerances,
)
from ._workspace import Workspace  # noqa: E402

__all__ = [
    "CommandFunction",
    "CommandMap",
    "batch_mesh",
    "command_function",
    "command_map",
    "run_batch",
    "DataFileError",
    "Measurements",
    "load_measurements",
    "save_measurements",
    "Calibration",
    "calibrate",
    "fit",
    "setup",
    "validate",
    "perturb_table",
    "plan_grid",
    "plan_random",
    "plan_swing",
    "plan_x_line",
    "simulate",
    "interferometer",
    "point_tracker",
    "tracker6",
    "PosteriorResult",
    "corner_plot",
    "plot_bands",
    "posterior",
    "predictive_bands",
    "compare_with_random",
    "evaluate_design",
    "pose_jacobians",
    "select_poses",
    "Diagnosis",
    "diagnose",
    "heldout_rms",
    "AbstractEffect",
    "Backlash",
    "Compliance",
    "Context",
    "EFFECTS",
    "PeriodicLead",
    "Rehoming",
    "Thermal",
    "leg_forces",
    "ErrorMap",
    "Grid",
    "LeadScale",
    "PoseList",
    "ToleranceFileError",
    "Tolerances",
    "error_map",
    "load_tolerances",
    "monte_carlo",
    "paper_error_jacobian",
    "pose_sensitivity",
    "save_tolerances",
    "workspace_slice",
    "ForwardOptions",
    "ForwardResult",
    "KinematicsError",
    "Spiral",
    "Table",
    "TableFileError",
    "Workspace",
    "actuator_command",
    "check_reachable",
    "check_table",
    "default_effects",
    "euler_rate_matrix",
    "forward",
    "forward_solve",
    "joint_bend",
    "leg_lengths",
    "load_model",
    "load_table",
    "paper_rod_rotation",
    "paper_rotation_matrix",
    "reachable",
    "reference_table",
    "replace",
    "rod_rotation",
    "rotation_matrix",
    "save_table",
    "spiral_extension",
    "symmetric_table",
    "table_from_dict",
]
__version__ = "0.1.0"
