"""Forward kinematics for ONE command: 6-D Newton (optimistix) with the effects inside."""

import equinox as eqx
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jaxtyping import Array, Float, Int

from ._effects import Effects
from ._model import length_residual
from ._table import Table


class ForwardOptions(eqx.Module):
    """Newton settings. The unknown is the pose with its angles multiplied by the platform
    radius, so both tolerances are in mm (for angles: mm of arc at the platform joints).
    Stopping rule (max norm): |Δy| < atol + rtol·|y| and |residual| < atol."""

    rtol: float = eqx.field(static=True, default=1e-13)
    atol: float = eqx.field(static=True, default=1e-10)
    max_steps: int = eqx.field(static=True, default=50)
    accept_residual: float = eqx.field(static=True, default=1e-8)


def angle_scale(table: Table) -> Float[Array, ""]:
    """Platform radius (mean |a_i^p|), mm: converts rad to mm of arc for the Newton unknown."""
    return jnp.mean(jnp.linalg.norm(table.platform_joints, axis=-1))


def forward_one(
    table: Table,
    effects: Effects,
    s: Float[Array, "6"],
    guess: Float[Array, "6"],
    options: ForwardOptions = ForwardOptions(),
) -> tuple[Float[Array, "6"], Int[Array, ""], Int[Array, ""], Float[Array, ""]]:
    """Pose q (6,) at which the table settles for actuator extensions `s` (6,), mm.

    Returns (pose, result code, Newton steps, max |residual| in mm). Result codes are
    optimistix's: 0 = converged, 2 = singular Jacobian, 1/7 = step limit, 8 = diverged.
    Differentiable in (table, effects, s) by implicit differentiation.
    """
    scale = jnp.concatenate([jnp.ones(3), jnp.full(3, angle_scale(table))])

    def fn(y, args):
        table, effects, s = args
        return length_residual(table, effects, y / scale, s)

    solver = optx.Newton(options.rtol, options.atol, linear_solver=lx.LU())
    args = (table, effects, s)
    sol = optx.root_find(fn, solver, guess * scale, args, max_steps=options.max_steps, throw=False)
    y = sol.value
    resid = jnp.max(jnp.abs(fn(y, args)))
    return y / scale, sol.result._value, sol.stats["num_steps"], resid
