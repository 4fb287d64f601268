"""Forward kinematics for ONE command: 6-D Newton (optimistix) with the effects inside."""

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float, Int

from ._context import Context
from ._effects import Effects
from ._linalg import SmallLU, solve_small
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


def _newton(table, effects, s, guess, ctx, options):
    """optimistix Newton on the scaled pose; no derivative (see `forward_one`)."""
    table, effects, s, guess, ctx = jax.lax.stop_gradient((table, effects, s, guess, ctx))
    scale = jnp.concatenate([jnp.ones(3), jnp.full(3, angle_scale(table))])

    def fn(y, args):
        table, effects, s, ctx = args
        return length_residual(table, effects, y / scale, s, ctx)

    solver = optx.Newton(options.rtol, options.atol, linear_solver=SmallLU())
    args = (table, effects, s, ctx)
    sol = optx.root_find(fn, solver, guess * scale, args, max_steps=options.max_steps, throw=False)
    y = sol.value
    resid = jnp.max(jnp.abs(fn(y, args)))
    code = sol.result._value
    ok = (code == 0) & jnp.all(jnp.isfinite(y))
    # a failed solve returns the guess (flagged by its code), never NaN, so derivatives and
    # optimisers that probe far-away parameters stay finite
    q = jnp.where(ok, y / scale, guess)
    return q, code, sol.stats["num_steps"], jnp.where(ok, resid, jnp.inf)


@partial(jax.custom_jvp, nondiff_argnums=(5,))
def _solve(table, effects, s, guess, ctx, options):
    return _newton(table, effects, s, guess, ctx, options)


@_solve.defjvp
def _solve_jvp(options, primals, tangents):
    """Implicit differentiation: r(q, θ, s) = 0 ⇒ dq = −(∂r/∂q)⁻¹ (∂r/∂θ dθ + ∂r/∂s ds),
    with a plain-jnp 6×6 solve (no LAPACK call, no error on a failed primal)."""
    table, effects, s, guess, ctx = primals
    t_table, t_effects, t_s, _, _ = tangents
    out = _newton(table, effects, s, guess, ctx, options)
    q = out[0]
    _, dr = jax.jvp(
        lambda t, e, s_: length_residual(t, e, q, s_, ctx),
        (table, effects, s),
        (t_table, t_effects, t_s),
    )
    Jq = jax.jacfwd(lambda qq: length_residual(table, effects, qq, s, ctx))(q)
    dq = -solve_small(Jq, dr[:, None])[:, 0]
    zero_int = np.zeros((), dtype=jax.dtypes.float0)
    return out, (dq, zero_int, zero_int, jnp.zeros_like(out[3]))


def forward_one(
    table: Table,
    effects: Effects,
    s: Float[Array, "6"],
    guess: Float[Array, "6"],
    options: ForwardOptions = ForwardOptions(),
    ctx: Context | None = None,
) -> tuple[Float[Array, "6"], Int[Array, ""], Int[Array, ""], Float[Array, ""]]:
    """Pose q (6,) at which the table settles for actuator extensions `s` (6,), mm.

    Returns (pose, result code, Newton steps, max |residual| in mm). Result codes are
    optimistix's: 0 = converged, 2 = singular Jacobian, 1/7 = step limit, 8 = diverged; a
    failed solve returns `guess` as its pose (check the code). Differentiable in (table,
    effects, s), forward and reverse mode, by implicit differentiation. `ctx`: the stop's
    context (direction, temperature, payload, session; default: home).
    """
    ctx = Context() if ctx is None else ctx
    return _solve(table, effects, s, guess, ctx, options)
