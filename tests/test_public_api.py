"""The public API: every name `import jaxtable` exposed before the restructure is still there
(add, don't break), and the deprecated spellings still work, with a warning."""

import numpy as np
import pytest
from conftest import random_poses

import jaxtable as jt

BEFORE = [
    "AbstractEffect",
    "Backlash",
    "Calibration",
    "CommandFunction",
    "CommandMap",
    "Compliance",
    "Context",
    "DataFileError",
    "Diagnosis",
    "EFFECTS",
    "ErrorMap",
    "ForwardOptions",
    "ForwardResult",
    "Grid",
    "KinematicsError",
    "LeadScale",
    "Measurements",
    "PeriodicLead",
    "PoseList",
    "PosteriorResult",
    "Rehoming",
    "Spiral",
    "Table",
    "TableFileError",
    "Thermal",
    "ToleranceFileError",
    "Tolerances",
    "Workspace",
    "actuator_command",
    "batch_mesh",
    "calibrate",
    "check_reachable",
    "check_table",
    "command_function",
    "command_map",
    "compare_with_random",
    "corner_plot",
    "default_effects",
    "diagnose",
    "error_map",
    "euler_rate_matrix",
    "evaluate_design",
    "fit",
    "forward",
    "forward_solve",
    "heldout_rms",
    "interferometer",
    "joint_bend",
    "leg_forces",
    "leg_lengths",
    "load_measurements",
    "load_model",
    "load_table",
    "load_tolerances",
    "monte_carlo",
    "paper_error_jacobian",
    "paper_rod_rotation",
    "paper_rotation_matrix",
    "perturb_table",
    "plan_grid",
    "plan_random",
    "plan_swing",
    "plan_x_line",
    "plot_bands",
    "point_tracker",
    "pose_jacobians",
    "pose_sensitivity",
    "posterior",
    "predictive_bands",
    "reachable",
    "reference_table",
    "replace",
    "rod_rotation",
    "rotation_matrix",
    "run_batch",
    "save_measurements",
    "save_table",
    "save_tolerances",
    "select_poses",
    "setup",
    "simulate",
    "spiral_extension",
    "symmetric_table",
    "table_from_dict",
    "tracker6",
    "validate",
    "workspace_slice",
]

ADDED = [
    "prior_check",
    "DetectionPower",
    "detection_power",
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
    "FittedModel",
    "InstrumentFrames",
    "Validation",
    "fitted_model",
    "load_fitted_model",
    "save_fitted_model",
    "GEOMETRY",
    "RESULTS",
    "align_pose_errors",
    "euler_from_matrix",
    "platform_radius",
    "pose_error",
    "reports",
    "rotation_log",
    # measured data and discovery beyond the library
    "Discovered",
    "NoiseEstimate",
    "StructureTest",
    "enable_compilation_cache",
    "parse_sigma",
    "structure_test",
    # a flexible residual model, and plans that tell ambiguous findings apart
    "DiscriminationPlan",
    "ResidualGP",
    "discrimination_plan",
    "residual_gp",
]


def test_every_earlier_public_name_is_still_exported():
    missing = [n for n in BEFORE if not hasattr(jt, n)]
    assert not missing, missing
    assert set(BEFORE) <= set(jt.__all__)


def test_all_lists_exactly_what_is_exported():
    assert all(hasattr(jt, n) for n in jt.__all__)
    assert set(jt.__all__) == set(BEFORE) | set(ADDED)
    assert len(jt.__all__) == len(set(jt.__all__))


def test_version_comes_from_package_metadata():
    from importlib.metadata import version

    assert jt.__version__ == version("jaxtable")


def test_old_compensate_keyword_warns_and_still_works(table):
    poses = random_poses(4, seed=1)
    new = np.asarray(jt.actuator_command(table, poses, compensated=False))
    with pytest.warns(DeprecationWarning, match="compensated"):
        old = np.asarray(jt.actuator_command(table, poses, compensate=False))
    np.testing.assert_array_equal(old, new)
    # and the flag means what it says: the rigid command is the leg lengths
    np.testing.assert_allclose(new, np.asarray(jt.leg_lengths(table, poses)), atol=1e-12)


def test_old_monte_carlo_argument_order_warns_and_gives_the_same(table):
    poses = random_poses(2, seed=2)
    new = jt.monte_carlo(table, jt.Tolerances(), poses, 8, seed=4)
    with pytest.warns(DeprecationWarning, match="monte_carlo"):
        old = jt.monte_carlo(table, poses, jt.Tolerances(), 8, seed=4)
    np.testing.assert_array_equal(old, new)


def test_forward_result_code_is_deprecated_in_favour_of_results(table):
    cmd = np.full((2, 6), float(table.zero_lengths[0]))
    cmd[1] = [600.0, 1060.0, 600.0, 1060.0, 600.0, 1060.0]
    res = jt.forward_solve(table, cmd)
    assert np.asarray(res.result == jt.RESULTS.successful).tolist() == [True, False]
    assert res.reason(0) == ""
    assert res.reason(1) != ""
    # one chunk per command: the result comes back through numpy, the messages the same
    per_row = jt.forward_solve(table, cmd, chunk=1)
    assert [per_row.reason(0), per_row.reason(1)] == [res.reason(0), res.reason(1)]
    with pytest.warns(DeprecationWarning, match="RESULTS"):
        code = np.asarray(res.code)
    assert code[0] == 0 and code[1] != 0


def test_import_leaves_the_heavy_libraries_to_the_calls_that_need_them():
    """`import jaxtable` (every command-line run, every study) imports neither matplotlib
    (figures), emcee (the posterior) nor scipy.stats (a few tests' p-values): ~1.5 s of
    imports that a run which does not use them would otherwise spend."""
    import subprocess
    import sys

    code = (
        "import sys, jaxtable; "
        "print(' '.join(m for m in ('matplotlib', 'emcee', 'scipy.stats') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", out.stdout
