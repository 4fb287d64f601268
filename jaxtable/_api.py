"""Public batched functions: input checks at the boundary, jitted vmap inside.

Every function takes poses of shape (..., 6) = (x, y, z, roll, pitch, yaw) in mm and rad
(any leading dims, float64) and returns per-leg arrays of shape (..., 6).
"""

import dataclasses
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from . import _kinematics as kin
from . import _rotation as rot
from ._batch import flatten_batch, run_batch
from ._context import Context, split_context
from ._effects import Effects, resolve_effects
from ._errors import (
    KinematicsError,
    check_finite_lengths,
    check_finite_poses,
    describe_rows,
    is_concrete,
    renamed_argument,
    require_x64,
)
from ._forward import CHORD_BELOW, RESULTS, ForwardOptions, forward_one
from ._jit import LARGE_BATCH, device_array
from ._model import inverse_extension
from ._table import Table


def per_pose(fn, table: Table, poses, chunk: int):
    require_x64()
    check_finite_poses(poses)
    flat, batch_shape = flatten_batch(poses, 1)
    out = run_batch(fn, table, flat, chunk=chunk)
    return jax.tree.map(lambda o: device_array(o, batch_shape + np.shape(o)[1:]), out)


def leg_lengths(table: Table, poses, *, chunk: int = 1 << 16) -> Float[ArrayLike, "... 6"]:
    """Joint-to-joint leg lengths |t + R a_i^p − b_i| of the rigid geometry, mm. (..., 6)."""
    return per_pose(kin.leg_lengths, table, poses, chunk)


def rod_rotation(table: Table, poses, *, chunk: int = 1 << 16) -> Float[ArrayLike, "... 6"]:
    """Rod-versus-barrel rotation Δα_i since home, rad, (..., 6). Right-hand rule about the
    leg axis (base -> platform): positive = counter-clockwise seen from the platform end."""
    return per_pose(kin.rod_rotation, table, poses, chunk)


def spiral_extension(table: Table, poses, *, chunk: int = 1 << 16) -> Float[ArrayLike, "... 6"]:
    """Passive spiral extension hand·lead·Δα_i/(2π), mm, (..., 6)."""
    return per_pose(kin.spiral_extension, table, poses, chunk)


def paper_rod_rotation(table: Table, poses, *, chunk: int = 1 << 16) -> Float[ArrayLike, "... 6"]:
    """The paper's literal eqs. (15)-(19), rad, (..., 6); opposite sense to `rod_rotation`.
    Kept only for comparison (see `jaxtable._kinematics.paper_rod_rotation`)."""
    return per_pose(kin.paper_rod_rotation, table, poses, chunk)


def joint_bend(table: Table, poses, *, chunk: int = 1 << 16) -> Float[ArrayLike, "... 2 6"]:
    """U-joint bend from the home leg direction, rad, (..., 2, 6): [base, platform]."""
    return per_pose(kin.joint_bend, table, poses, chunk)


def pose_error(actual, commanded) -> Float[ArrayLike, "... 6"]:
    """Error of poses `actual` against `commanded` (both (..., 6), mm / rad, broadcast):
    translation difference (mm) and the rotation vector of R(actual) R(commanded)ᵀ (rad,
    base frame), (..., 6). jaxtable's one pose-error measure (see `_rotation.pose_error`)."""
    require_x64()
    xp = np if is_concrete(actual, commanded) else jnp  # numpy: no eager programs
    a = xp.asarray(actual, dtype=np.float64)
    c = xp.asarray(commanded, dtype=np.float64)
    shape = np.broadcast_shapes(a.shape, c.shape)
    if shape[-1:] != (6,):
        raise ValueError(f"poses must have shape (..., 6); got {a.shape} and {c.shape}")
    a, c = (xp.broadcast_to(x, shape).reshape(-1, 6) for x in (a, c))
    return device_array(run_batch(_pose_error_row, None, (a, c)), shape)


def _pose_error_row(_, row):
    return rot.pose_error(*row)


def _reach_one(table, pose):
    L, base, platform = kin._lengths_and_bends(table, pose)
    return L, jnp.maximum(base, platform)


def reachable(table: Table, poses, *, chunk: int = 1 << 16):
    """Boolean (...,): every leg inside the stroke and every U-joint bend within the limit."""
    return per_pose(kin.within_limits, table, poses, chunk)


def check_reachable(table: Table, poses, *, chunk: int = 1 << 16) -> None:
    """Raise KinematicsError naming every pose (first few) outside the stroke or joint limits."""
    L, bend = per_pose(_reach_one, table, poses, chunk)
    L, bend = np.asarray(L).reshape(-1, 6), np.asarray(bend).reshape(-1, 6)
    lo, hi = (float(v) for v in np.asarray(table.stroke))
    limit = float(table.joint_angle_limit)
    out_stroke = ~np.asarray(kin.in_stroke(table, L))
    out_bend = bend > limit
    bad = out_stroke.any(1) | out_bend.any(1)
    if bad.any():

        def what(i):
            parts = [
                f"leg {k + 1} length {L[i, k]:.3f} mm outside stroke [{lo}, {hi}]"
                for k in np.flatnonzero(out_stroke[i])
            ] + [
                f"leg {k + 1} joint bend {np.rad2deg(bend[i, k]):.2f} deg > limit "
                f"{np.rad2deg(limit):.2f} deg"
                for k in np.flatnonzero(out_bend[i])
            ]
            return "; ".join(parts)

        batch_shape = np.shape(poses)[:-1]
        raise KinematicsError("pose(s) unreachable:\n" + describe_rows(bad, batch_shape, what))


def _check_stroke(table: Table, lengths, batch_shape, name: str) -> None:
    if not is_concrete(table, lengths):
        return
    L = np.asarray(lengths).reshape(-1, 6)
    lo, hi = (float(v) for v in np.asarray(table.stroke))
    out = ~np.asarray(kin.in_stroke(table, L))
    if out.any():

        def what(i):
            return "; ".join(
                f"leg {k + 1} {L[i, k]:.3f} mm outside stroke [{lo}, {hi}]"
                for k in np.flatnonzero(out[i])
            )

        raise KinematicsError(
            f"{name} outside the stroke:\n" + describe_rows(out.any(1), batch_shape, what)
        )


def _command_row(shared, row):
    """Commanded joint-to-joint lengths L0 + s (6,) for one pose (the row function of
    `actuator_command`): shared = (table, effects, context or None), row = (pose, context
    or None)."""
    table, effects, ctx = shared
    pose, row_ctx = row
    s, _ = inverse_extension(table, effects, pose, row_ctx if ctx is None else ctx)
    return table.zero_lengths + s


def actuator_command(
    table: Table,
    poses,
    compensated: bool = True,
    *,
    compensate: bool | None = None,
    effects: Effects | None = None,
    context: Context | None = None,
    check: bool = True,
    chunk: int = 1 << 20,
) -> Float[ArrayLike, "... 6"]:
    """Joint-to-joint leg lengths the controller should command for `poses`, mm, (..., 6).

    `compensated=False`: the rigid inverse kinematics |l_i(q)| (what an uncompensated
    controller commands). `compensated=True`: the command L0_i + s_i for which the hardware,
    with its effects (default: the table's own, i.e. the passive spiral term), reaches the
    pose: the paper's Δl* = Δl − Δl2 for the spiral term. The actuator extension is
    s_i = command_i − L0_i. `context`: the stops' context (a `Context` for all, or one with a
    leading axis of the flattened batch; default: home context).

    With `check=True` (default) a non-finite pose or a command outside the stroke raises
    KinematicsError naming the pose and leg.
    """
    require_x64()
    check_finite_poses(poses)
    compensated = renamed_argument(
        compensated, compensate, "compensate", "compensated", "actuator_command"
    )
    eff = resolve_effects(table, effects) if compensated else {}
    flat, batch_shape = flatten_batch(poses, 1)
    shared_ctx, row_ctx = split_context(flat.shape[0], context)
    cmd = run_batch(_command_row, (table, eff, shared_ctx), (flat, row_ctx), chunk=chunk)
    if check:
        _check_stroke(table, cmd, batch_shape, "commanded leg length(s)")
    return device_array(cmd, batch_shape + (6,))


class ForwardResult(eqx.Module):
    """Per-command outcome of `forward_solve`. Shapes: pose (..., 6); result, steps,
    residual (...). `result` is a batched `RESULTS` item: compare it with
    `RESULTS.successful` (elementwise), or read `ok`; `reason(i)` is the message of the
    i-th command (flat index)."""

    pose: Float[ArrayLike, "... 6"]
    result: RESULTS
    steps: Array
    residual: Float[ArrayLike, "..."]

    @property
    def ok(self):
        """Boolean (...): the solve converged to a physical pose within tolerance."""
        if is_concrete(self.result):  # in numpy: an eager comparison compiles per shape
            (code,), (success,) = jax.tree.leaves(self.result), jax.tree.leaves(RESULTS.successful)
            return device_array(np.asarray(code) == np.asarray(success))
        return self.result == RESULTS.successful

    def reason(self, i: int) -> str:
        """The `RESULTS` message of command `i` (index into the flattened batch)."""
        # a 0-d numpy array: RESULTS names only array values (a numpy scalar, which a batch
        # of several chunks returned, read "unknown")
        return RESULTS[jax.tree.map(lambda v: np.asarray(np.reshape(v, -1)[i]), self.result)]

    @property
    def code(self):
        """Deprecated: integer result codes (0 = converged). Compare `result` with
        `jaxtable.RESULTS` members instead; `code` will be removed in the next release."""
        warnings.warn(
            "ForwardResult.code is deprecated; compare ForwardResult.result with "
            "jaxtable.RESULTS members (or use .ok)",
            DeprecationWarning,
            stacklevel=2,
        )
        return jax.tree.leaves(self.result)[0]


FORWARD_CHUNK = 1 << 15
"""Default chunk of the forward solve. On the CPU a chunk runs as per-core pieces of
128-row blocks (`_batch`), so the Newton loop's Jacobians and eliminations stay in cache
whatever the chunk; larger chunks then mean fewer calls (10⁶ poses on 2 cores: 2.6–2.7×10⁵
poses/s with 8192, 2.8–3.3×10⁵ with 16384–65536)."""


def _forward_row(shared, row):
    """(pose, result, steps, residual) for one command (the row function of
    `forward_solve`): shared = (table, effects, options, guess or None, context or None),
    row = (s, guess or None, context or None)."""
    table, effects, options, guess, ctx = shared
    s, row_guess, row_ctx = row
    guess = row_guess if guess is None else guess
    ctx = row_ctx if ctx is None else ctx
    return forward_one(table, effects, s, guess, options, ctx)


def forward_solve(
    table: Table,
    commands,
    *,
    effects: Effects | None = None,
    guess=None,
    nominal: Table | None = None,
    context: Context | None = None,
    options: ForwardOptions = ForwardOptions(),
    chunk: int = FORWARD_CHUNK,
) -> ForwardResult:
    """Forward kinematics without raising: the pose and a status for every command.

    Use `forward` unless you want to handle failures pose by pose (`ok`, `result`).
    """
    require_x64()
    check_finite_lengths(commands)
    eff = resolve_effects(table, effects)
    flat, batch_shape = flatten_batch(commands, 1)
    zero = (table if nominal is None else nominal).zero_lengths
    s = flat - (np.asarray(zero) if is_concrete(flat, zero) else zero)  # numpy where concrete
    n = flat.shape[0]
    large = n >= LARGE_BATCH  # smaller batches: plain Newton, the quickest to compile
    if guess is None:
        guess = np.zeros(6)
    else:
        check_finite_poses(guess, "guess")
        guess = (np if is_concrete(guess) else jnp).asarray(guess, dtype=np.float64)
    if guess.ndim > 1 or not large:  # per row; a small batch's always, as its context
        # (`split_context`): one compiled kernel whatever their kinds. numpy where concrete:
        # an eager jnp op compiles a program per shape
        guess = (np if is_concrete(guess) else jnp).broadcast_to(guess.reshape(-1, 6), (n, 6))
    shared_guess, row_guess = (guess, None) if guess.ndim == 1 else (None, guess)
    if options.peel_first_step is None:  # one first step for the batch (see ForwardOptions)
        options = dataclasses.replace(options, peel_first_step=large and shared_guess is not None)
    if options.chord_below is None:
        options = dataclasses.replace(options, chord_below=CHORD_BELOW if large else 0.0)
    shared_ctx, row_ctx = split_context(n, context)
    out = run_batch(
        _forward_row,
        (table, eff, options, shared_guess, shared_ctx),
        (s, row_guess, row_ctx),
        chunk=chunk,
    )
    pose, result, steps, resid = out
    return ForwardResult(
        device_array(pose, batch_shape + (6,)),
        jax.tree.map(lambda v: device_array(v, batch_shape), result),
        device_array(steps, batch_shape),
        device_array(resid, batch_shape),
    )


def forward(
    table: Table,
    commands,
    *,
    effects: Effects | None = None,
    guess=None,
    nominal: Table | None = None,
    context: Context | None = None,
    options: ForwardOptions = ForwardOptions(),
    chunk: int = FORWARD_CHUNK,
) -> Float[ArrayLike, "... 6"]:
    """Pose (..., 6) the table reaches for commanded joint-to-joint lengths (..., 6), mm.

    The actuator extension is s_i = command_i − L0_i, with L0 of the table the controller
    believes (`nominal`, default `table` itself: pass the nominal table to move a hardware
    table that differs from it); the pose q solves
    |l_i(q)| = L0_i + s_i + Σ effects_i(q, s) by Newton (optimistix) from `guess` (default:
    home), with the effects (default: the table's hardware effects, i.e. the passive spiral
    term; `{}` = rigid) inside the solve, evaluated in `context` (a `Context`, batched over
    the flattened commands or shared; default: home). Differentiable by implicit
    differentiation.

    Raises KinematicsError, naming the pose(s) and the reason, for non-finite commands,
    commands outside the stroke, non-convergence, a singular Jacobian or a non-physical
    solution. Inside `jit`/`grad` the same failures raise through `eqx.error_if`.
    """
    flat_shape = np.shape(commands)[:-1]
    if is_concrete(commands):
        check_finite_lengths(commands)
        _check_stroke(table, commands, flat_shape, "commanded leg length(s)")
    res = forward_solve(
        table,
        commands,
        effects=effects,
        guess=guess,
        nominal=nominal,
        context=context,
        options=options,
        chunk=chunk,
    )
    if is_concrete(res):
        bad = ~np.asarray(res.ok).reshape(-1)
        if np.any(bad):
            resid = np.asarray(res.residual).reshape(-1)
            steps = np.asarray(res.steps).reshape(-1)

            def what(i):
                return f"{res.reason(i)} (after {int(steps[i])} steps, residual {resid[i]:.3g} mm)"

            raise KinematicsError(
                "forward kinematics failed:\n" + describe_rows(bad, flat_shape, what)
            )
        return res.pose
    return eqx.error_if(
        res.pose,
        jnp.any(~res.ok),
        "forward kinematics failed for at least one command (call forward_solve for results)",
    )
