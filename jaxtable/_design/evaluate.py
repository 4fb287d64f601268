"""Evaluating designs over a required workspace: one design with every criterion and its
per-pose maps (`assess`), or a stack of designs at once (`assess_batch`, vmap over designs)."""

from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import ArrayLike, Float

from .._analysis.workspaces import PoseList, Workspace
from .._batch import _pad_rows, run_batch
from .._errors import TableFileError, is_concrete
from .._jit import jit
from .._table import Table
from .criteria import (
    aggregate,
    criteria,
    first_frequency,
    pose_criteria,
    stiffness_matrix,
    tolerance_cost,
)
from .hardware import Hardware, hardware_for
from .variables import Design, check_design


def design_poses(
    workspace: "Workspace | PoseList | np.ndarray | None" = None,
    n_sweep: int = 11,
    n_random: int = 256,
    seed: int = 0,
    box: int = 3,
) -> np.ndarray:
    """The poses a design is judged on (N, 6), mm / rad. For a `Workspace` (default: the
    reference table's): each DOF alone at `n_sweep` points over its single-DOF range, a
    `box`⁶ grid over the combined box (3: corners, edge and face centres; 2: corners), and
    `n_random` uniform poses in it (11, 256, 3: 1051 poses). A `PoseList` or an (N, 6)
    array is used as given."""
    if workspace is None:
        workspace = Workspace()
    if isinstance(workspace, Workspace):
        return np.concatenate(
            [workspace.sweeps(n_sweep).reshape(-1, 6), workspace.box_samples(n_random, seed, box)]
        )
    if isinstance(workspace, PoseList):
        return workspace.poses()
    return np.asarray(workspace, dtype=float).reshape(-1, 6)


def as_design(design: "Design | Table", hardware: Hardware | None = None) -> Design:
    """A `Design` from a design or a bare table (its leaves then are the variables);
    `hardware` default: `hardware_for(table)`."""
    if isinstance(design, Design):
        return design if hardware is None else eqx.tree_at(lambda d: d.hardware, design, hardware)
    return Design(design, hardware_for(design) if hardware is None else hardware)


def _pose_row(shared, pose):
    table, hw = shared
    return pose_criteria(table, hw, pose)


# compiled forms of the small whole-design functions; the per-pose kernel runs through
# `run_batch` (its compiled sizes shared between pose counts)
_aggregate = jit(aggregate)
_first_frequency = jit(first_frequency)
_stiffness_matrix = jit(stiffness_matrix)
_tolerance_cost = jit(tolerance_cost)


def evaluate(
    table: Table, hw: Hardware, poses, smooth=None, coverage_width: Float[ArrayLike, ""] = 1.0
) -> tuple[dict, dict]:
    """(`criteria(table, hw, poses, smooth, coverage_width)`, the per-pose quantities of
    `pose_criteria` ((N,) each)) for concrete input: the per-pose kernel once through
    `run_batch`, the workspace aggregates from its output (`smooth` and `coverage_width`
    enter as numbers, so every smoothing shares one small compiled program)."""
    per = run_batch(_pose_row, (table, hw), np.asarray(poses, dtype=float).reshape(-1, 6))
    p = None if smooth is None else jnp.asarray(smooth, dtype=jnp.float64)
    out = dict(_aggregate(per, p, jnp.asarray(coverage_width, dtype=jnp.float64)))
    out["first_frequency_Hz"] = _first_frequency(table, hw)
    out["tolerance_cost"] = _tolerance_cost(hw.tolerances)
    return out, per


def design_criteria(
    table: Table,
    hw: Hardware,
    poses: Float[ArrayLike, "N 6"],
    smooth=None,
    coverage_width: Float[ArrayLike, ""] = 1.0,
) -> dict:
    """Every criterion of CRITERIA (scalars) of one design over the required poses (N, 6),
    mm / rad; `smooth=p` gives the smoothed worst cases an optimiser should follow (see
    `criteria`). Differentiable in every leaf of `table` and `hw`: inside a user's jit, vmap
    or grad it is `criteria`, traced inline; called with concrete values it runs compiled
    (`evaluate`; op by op, a first call compiled ~270 small programs)."""
    if not is_concrete(table, hw, poses, smooth, coverage_width):
        return criteria(table, hw, poses, smooth, coverage_width)
    return evaluate(table, hw, poses, smooth, coverage_width)[0]


@dataclass
class Assessment:
    """Every criterion of one design (`values`, CRITERIA keys, floats in their units), the
    stiffness at home (6, 6), and the per-pose quantities of `pose_criteria` ((N,) numpy each)
    at the required `poses` (N, 6)."""

    design: Design
    poses: np.ndarray
    values: dict
    stiffness_home: np.ndarray
    per_pose: dict = field(repr=False)


def assess(
    design: "Design | Table",
    hardware: Hardware | None = None,
    workspace=None,
    *,
    n_sweep: int = 11,
    n_random: int = 256,
    seed: int = 0,
) -> Assessment:
    """Evaluate one design over the required workspace (see `design_poses`). Refuses a design
    outside physical limits (naming the variable) and a workspace it cannot reach at all."""
    design = as_design(design, hardware)
    check_design(design)
    poses = design_poses(workspace, n_sweep, n_random, seed)
    table = design.table()
    values, per_pose = evaluate(table, design.hardware, poses)
    values = {k: float(v) for k, v in values.items()}
    per_pose = {k: np.asarray(v) for k, v in per_pose.items()}
    if values["coverage"] == 0.0:
        worst = float(np.max(-per_pose["margin"]))
        raise TableFileError(
            f"workspace: not one of its {len(poses)} required poses is within the limits of "
            f"'{table.name}' (stroke {np.asarray(table.stroke).tolist()} mm, joint bend limit "
            f"{np.rad2deg(float(table.joint_angle_limit)):g} deg); the nearest misses by "
            f"{worst:.4g} mm"
        )
    K = np.asarray(_stiffness_matrix(table, jnp.zeros(6), design.hardware.leg_stiffness))
    return Assessment(design, poses, values, K, per_pose)


DESIGN_CHUNK = 64
"""Designs per compiled call of `assess_batch`: a design's row is every criterion over all
the poses (~8 ms for 1000 poses), so a few dozen designs a call already amortise the call;
a stack of up to 64 designs runs as the next power of two (at least 8), a larger one in
chunks of 64 (its last one padded), so stacks of any size share four compiled programs at
most for given poses (each takes seconds to compile; the optimiser's stacks of finals
differ in size from call to call)."""


def _design_row(shared, design: Design):
    """Every criterion of one design (the row function of `assess_batch`)."""
    poses, smooth = shared
    return criteria(design.table(), design.hardware, poses, smooth)


def assess_batch(
    designs: Design, poses, smooth: float | None = None, *, chunk: int = DESIGN_CHUNK
) -> dict:
    """Criteria of a stack of designs (leaves with a leading design axis, see
    `variables.stack`) over the same poses (N, 6): {name: (D,) numpy}. vmapped over designs
    and poses, `chunk` designs a call (`DESIGN_CHUNK`; `_batch.run_batch`'s padding); jax
    arrays inside a trace."""
    poses = jnp.asarray(poses, dtype=jnp.float64)
    if not is_concrete(designs, poses):
        return run_batch(_design_row, (poses, smooth), designs, chunk=chunk)
    designs = jax.tree.map(np.asarray, designs)
    n = jax.tree.leaves(designs)[0].shape[0]
    if n > chunk:  # whole chunks: the equal chunks run_batch cuts are then `chunk` designs
        designs = _pad_rows(designs, -(-n // chunk) * chunk)
    out = run_batch(_design_row, (poses, smooth), designs, chunk=chunk, min_rows=8)
    return {k: np.asarray(v)[:n] for k, v in out.items()}
